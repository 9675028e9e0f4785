"""The output-folder rule shared by refine, baseline, simulate and demo: non-empty folders need --force, --force
removes only a previous run's files, --resume checks the checkpoint's inputs and config, one run at a time per
folder, and a failed run leaves nothing behind."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case, write_planar_sequence

from dm2_backend.cli.main import cli
from dm2_backend.pipeline.run_folder import CHECKPOINT, LOCK, MARKER, adding_to, open_folder, run_folder
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import write_sequence

SMALL = {"seed": 3, "frames": {"max_points": 128},
         "optimiser": {"points_per_frame": 32, "bce_points_per_frame": 16, "batch_groups": 16,
                       "grid_max_cells": 2**12, "dense": False}}  # the first-order epochs, checkpointed


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return write_planar_sequence(tmp_path_factory.mktemp("seq"), SMALL)


def dm2(*args: str):
    return CliRunner().invoke(cli, [*args], obj={})


def refine(seq: Path, out: Path, *extra: str):
    return dm2("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"),
               "--out", str(out), "-c", str(seq / "config.yaml"), "-q", "--no-cache", "--epochs", "1", *extra)


def one_line(result, *words: str) -> str:
    assert result.exit_code == 2, result.output + repr(result.exception)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dm2: error:"), result.output
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def done(seq, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("done") / "run"
    result = refine(seq, out)
    assert result.exit_code == 0, result.output
    return out


def test_a_finished_run_lists_its_files_and_releases_the_folder(done):
    marker = json.loads((done / MARKER).read_text())
    assert marker["command"] == "refine"
    assert {"report.json", "poses_tum.txt", CHECKPOINT, "prior"} <= set(marker["files"])
    assert not (done / LOCK).exists()


def test_a_non_empty_folder_is_refused_and_left_as_it_was(seq, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    one_line(refine(seq, out), "not empty", "--force")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_force_replaces_the_previous_runs_files_and_keeps_the_users(seq, done, tmp_path):
    out = tmp_path / "run"
    assert refine(seq, out).exit_code == 0
    (out / "notes.txt").write_text("my notes")
    one_line(dm2("baseline", "gtsam", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"),
                 "--out", str(out), "-q", "--no-cache"), "not empty")
    result = dm2("baseline", "gtsam", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"),
                 "--out", str(out), "-q", "--no-cache", "--force")
    assert result.exit_code == 0, result.output
    assert not (out / CHECKPOINT).exists()  # the refine's checkpoint does not sit beside the gtsam report
    assert (out / "notes.txt").read_text() == "my notes"
    assert json.loads((out / "report.json").read_text())["method"] == "gtsam"
    assert json.loads((out / MARKER).read_text())["command"] == "baseline"


def test_resume_needs_a_checkpoint(seq, tmp_path):
    out = tmp_path / "empty"
    one_line(refine(seq, out, "--resume"), "--resume", CHECKPOINT)
    assert not out.exists()  # the failed command left nothing behind


@pytest.mark.parametrize("change, named", [(("--seed", "4"), "seed"), (("--max-diff", "0.02"), None)])
def test_resume_names_what_changed(seq, done, change, named):
    result = refine(seq, done, "--resume", *change)
    if named is None:  # an option that changes nothing of the checkpoint resumes
        assert result.exit_code == 0, result.output
    else:
        one_line(result, "--resume", named)


def test_resume_refuses_another_config(seq, done, tmp_path):
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({**SMALL, "optimiser": {**SMALL["optimiser"], "lr_pose": 0.5}}))
    before = (done / "config.yaml").read_text()
    result = dm2("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--out",
                 str(done), "-c", str(other), "-q", "--no-cache", "--epochs", "1", "--resume")
    one_line(result, "optimiser.lr_pose")
    assert (done / "config.yaml").read_text() == before


def test_resume_refuses_other_scans(seq, done, tmp_path):
    case = planar_case()
    other = tmp_path / "other"
    write_sequence(other, case.scans[:-3], case.gt[:-3], case.warm[:-3], 10.0)
    result = dm2("refine", "--scans", str(other / "velodyne"), "--poses", str(other / "warm_start.txt"), "--out",
                 str(done), "-c", str(seq / "config.yaml"), "-q", "--no-cache", "--epochs", "1", "--resume")
    one_line(result, "--resume", "scans")


def test_a_folder_being_written_is_refused(seq, tmp_path):
    out = tmp_path / "busy"
    held = open_folder(out, "refine")
    try:
        one_line(refine(seq, out, "--force"), "another dm2 run", "writing")
    finally:
        held.release()
    assert not (out / LOCK).exists()


def test_two_simulations_into_one_folder_at_once(tmp_path):
    """Two real processes: one writes the folder, the other gets one line and exit 2."""
    out = tmp_path / "sim"
    cmd = [sys.executable, "-m", "dm2_backend", "simulate", "--planar", "--frames", "40", "-q", "--force",
           "--out", str(out)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(120), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes in ([0, 0], [0, 2]), results
    if codes == [0, 2]:
        err = next(e for code, e in results if code == 2)
        assert "another dm2 run" in err and len(err.strip().splitlines()) == 1
    assert len(list((out / "velodyne").glob("*.bin"))) == 40
    assert json.loads((out / MARKER).read_text())["command"] == "simulate"


def test_a_failed_run_leaves_nothing_behind(tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 zero\n")
    out = tmp_path / "new"
    assert dm2("baseline", "gtsam", "--graph", str(bad), "--out", str(out)).exit_code == 2
    assert not out.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("x")
    assert dm2("baseline", "gtsam", "--graph", str(bad), "--out", str(kept), "--force").exit_code == 2
    assert sorted(p.name for p in kept.iterdir()) == ["notes.txt"]


def test_an_output_under_a_file_is_one_line(seq, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    one_line(refine(seq, blocker / "run"), "is a file")
    one_line(refine(seq, blocker), "not a folder")


def test_an_interrupted_run_keeps_its_folder_for_resume(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt), run_folder(out, "refine"):
        with atomic_write(out / CHECKPOINT, "wb") as fh:  # as dm2 writes every output
            fh.write(b"state")
        raise KeyboardInterrupt
    assert (out / CHECKPOINT).exists()
    assert CHECKPOINT in json.loads((out / MARKER).read_text())["files"]
    with pytest.raises(InputError, match="not empty"):
        open_folder(out, "refine")


def test_files_added_to_a_finished_run_are_listed_and_locked(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "refine"), atomic_write(out / "report.json") as fh:
        fh.write("{}")
    with adding_to(out):
        with atomic_write(out / "map.pgm", "wb") as fh:
            fh.write(b"P5")
        with pytest.raises(InputError, match="another dm2 run"):
            open_folder(out, "refine", force=True)
    assert {"report.json", "map.pgm"} <= set(json.loads((out / MARKER).read_text())["files"])
    open_folder(out, "baseline", force=True).release()  # --force now replaces both
    assert not (out / "map.pgm").exists() and not (out / "report.json").exists()


def test_two_refines_into_one_folder_at_once(seq, tmp_path):
    """Two real refine processes into one --out: never both 'wrote'; the folder holds one run, whole."""
    out = tmp_path / "shared"
    cmd = [sys.executable, "-m", "dm2_backend", "refine", "--scans", str(seq / "velodyne"), "--poses",
           str(seq / "warm_start.txt"), "-c", str(seq / "config.yaml"), "--epochs", "1", "-q", "--no-cache",
           "--force", "--out", str(out)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(300), p.stdout.read(), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _, _ in results)
    assert codes in ([0, 0], [0, 2]), results  # [0, 0]: the second started after the first had finished
    for code, stdout, stderr in results:
        if code == 2:
            assert "another dm2 run" in stderr and "wrote" not in stdout
    report = json.loads((out / "report.json").read_text())
    marker = json.loads((out / MARKER).read_text())
    assert marker["command"] == "refine" and {"report.json", "poses.npy", "config.yaml"} <= set(marker["files"])
    assert report["frames"] == len(np.load(out / "poses.npy")) and not (out / LOCK).exists()
    assert not list(out.glob(".tmp-*"))
