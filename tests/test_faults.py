"""Faults (issue 31, and item 2 of issue 30): a marker never reaches outside --out, the user's files are never
replaced, a full disk is one line, signals end a run like Ctrl-C and name the next command, stale cache
entries are seen by content. Real processes where the fault is one of a process (signals, kill -9, limits)."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner
from optim_cases import one_thread, write_planar_sequence

from dm2_backend.cli.main import cli
from dm2_backend.optim.dense_checkpoint import DENSE_CHECKPOINT
from dm2_backend.pipeline.run_folder import CHECKPOINT, LOCK, MARKER
from dm2_backend.prepare.cache_keys import file_fingerprint

SMALL = {"seed": 3, "frames": {"max_points": 128},
         "optimiser": {"points_per_frame": 32, "bce_points_per_frame": 16, "batch_groups": 16,
                       "grid_max_cells": 2**12, "dense": False}}  # the first-order epochs, checkpointed
#: a child process that runs ``dm2 ARGS`` and, when the N-th output whose name matches PATTERN is about to be
#: written, sends itself SIGNAL (the instant of a real signal, chosen by what the run writes, not by a clock)
CHILD = """
import fnmatch, os, signal, sys
from pathlib import Path
from dm2_backend.runtime import atomic
from dm2_backend.cli.main import main
pattern, signame, nth = sys.argv[1], sys.argv[2], int(sys.argv[3])
seen = [0]
original = atomic._prepare
def _prepare(path, *args, **kwargs):
    if fnmatch.fnmatch(Path(path).name, pattern):
        seen[0] += 1
        if seen[0] == nth:
            os.kill(os.getpid(), getattr(signal, signame))
    return original(path, *args, **kwargs)
atomic._prepare = _prepare
sys.argv = ["dm2", *sys.argv[4:]]
main()
"""


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return write_planar_sequence(tmp_path_factory.mktemp("seq"), SMALL)


def refine_args(seq: Path, out: Path, *extra: str) -> list[str]:
    return ["refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--out", str(out),
            "-c", str(seq / "config.yaml"), "-q", "--epochs", "1", *extra]


def dm2(*args: str):
    return CliRunner().invoke(cli, list(args), obj={})


def one_line(result, *words: str) -> str:
    assert result.exit_code == 2, result.output + repr(result.exception)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dm2: error:"), result.output
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def child(args: list[str], *, pattern: str = "-", signame: str = "SIGTERM", nth: int = 0, limits=None,
          timeout: float = 300) -> subprocess.CompletedProcess:
    """``dm2 args`` in a real process (see :data:`CHILD`), optionally under resource ``limits``."""
    def preexec():
        # a child as a shell starts it: the signals it is sent neither blocked nor ignored, whatever state the test
        # process was left in (a mask or disposition is inherited across exec)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        for which, value in (limits or {}).items():
            resource.setrlimit(which, (value, value))

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", CHILD, pattern, signame, str(nth), *args], capture_output=True,
                          text=True, timeout=timeout, preexec_fn=preexec, env=env)


def last_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    return lines[-1] if lines else ""


# ----------------------------------------------------------------------- 1. the marker is input


def test_force_never_removes_what_a_marker_names_outside_the_folder(seq, tmp_path):
    victim = tmp_path / "victim_dir"
    (victim / "deep").mkdir(parents=True)
    (victim / "deep" / "precious.txt").write_text("mine")
    absolute = tmp_path / "elsewhere.txt"
    absolute.write_text("mine too")
    out = tmp_path / "mk"
    out.mkdir()
    (out / "report.json").write_text("{}")
    for files in (["../victim_dir", "report.json"], [str(absolute)], ["sub/../../victim_dir"], [".."]):
        (out / MARKER).write_text(json.dumps({"command": "refine", "files": files}))
        one_line(dm2(*refine_args(seq, out, "--force", "--no-cache")), MARKER, "plain name")
    assert (victim / "deep" / "precious.txt").read_text() == "mine" and absolute.read_text() == "mine too"
    assert (out / "report.json").exists()  # refused whole: nothing removed, not even what it may list


def test_force_leaves_a_listed_output_replaced_by_a_link_and_its_target(seq, tmp_path):
    target = tmp_path / "target"
    target.mkdir()
    (target / "keep.txt").write_text("mine")
    out = tmp_path / "run"
    assert dm2(*refine_args(seq, out, "--no-cache")).exit_code == 0
    marker = json.loads((out / MARKER).read_text())
    (out / "prior").rename(out / "prior.bak")
    shutil.rmtree(out / "prior.bak")
    (out / "prior").symlink_to(target, target_is_directory=True)
    (out / MARKER).write_text(json.dumps(marker))
    result = dm2(*refine_args(seq, out, "--no-cache", "--force"))
    assert result.exit_code == 2 and "no longer holds what it wrote" in result.output
    assert (target / "keep.txt").read_text() == "mine"
    assert (out / "prior").is_symlink()  # not what dm2 wrote there: left, and not followed


# ------------------------------------------------------------------- 2. the user's files stay theirs


@pytest.mark.parametrize("name", ["config.yaml", "poses_tum.txt", "report.json"])
def test_force_never_replaces_a_users_file_of_an_output_name(seq, tmp_path, name):
    out = tmp_path / "home"
    out.mkdir()
    (out / name).write_text("my own file")
    line = one_line(dm2(*refine_args(seq, out, "--force", "--no-cache")), name, "never replaces")
    assert "--out" in line
    assert sorted(p.name for p in out.iterdir()) == [name] and (out / name).read_text() == "my own file"


def test_a_users_file_beside_a_previous_run_is_kept_by_force(seq, tmp_path):
    out = tmp_path / "run"
    assert dm2(*refine_args(seq, out, "--no-cache")).exit_code == 0
    marker = json.loads((out / MARKER).read_text())
    marker["files"].remove("config.yaml")  # as if the user had put their own config.yaml there
    (out / MARKER).write_text(json.dumps(marker))
    (out / "config.yaml").write_text("mine")
    one_line(dm2(*refine_args(seq, out, "--force", "--no-cache")), "config.yaml", "never replaces")
    assert (out / "config.yaml").read_text() == "mine"


def test_dm2_map_never_replaces_a_users_file_in_a_run_folder(seq, tmp_path):
    out = tmp_path / "run"
    assert dm2(*refine_args(seq, out, "--no-cache")).exit_code == 0
    marker = json.loads((out / MARKER).read_text())
    assert "map.pgm" in marker["files"]
    marker["files"].remove("map.pgm")  # as if map.pgm were the user's own
    (out / MARKER).write_text(json.dumps(marker))
    (out / "map.pgm").write_text("my map")
    result = dm2("map", str(out), "--scans", str(seq / "velodyne"))
    assert result.exit_code == 2, result.output
    line = last_line(result.output)
    assert line.startswith("dm2: error:") and "map.pgm" in line and "never replaces" in line, line
    assert (out / "map.pgm").read_text() == "my map" and not (out / LOCK).exists()


def test_a_run_killed_while_writing_its_outputs_has_listed_them(seq, tmp_path):
    """kill -9 as the report (the last output) is about to be written: the marker already lists every file the
    run wrote, so --force replaces all of them and the new marker lists the whole new run."""
    out = tmp_path / "run"
    killed = child(refine_args(seq, out, "--no-cache"), pattern="report.json", signame="SIGKILL", nth=1)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    marker = json.loads((out / MARKER).read_text())
    present = {p.name for p in out.iterdir()} - {MARKER, LOCK}
    assert {"config.yaml", CHECKPOINT, "poses_tum.txt"} <= present
    assert present <= set(marker["files"]), present - set(marker["files"])
    again = dm2(*refine_args(seq, out, "--no-cache", "--force"))
    assert again.exit_code == 0, again.output
    marker = json.loads((out / MARKER).read_text())
    assert {p.name for p in out.iterdir()} - {MARKER} == set(marker["files"])


# ------------------------------------------------------------------------------------ 3. disk full


def _tmpfs_available() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-Urm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                           capture_output=True, timeout=30)
    return probe.returncode == 0


@pytest.mark.skipif(not _tmpfs_available(), reason="needs unshare -Urm to mount a small tmpfs")
@pytest.mark.parametrize("full", ["out", "cache", "zero"])
def test_a_full_disk_is_one_line_and_leaves_nothing_half_written(seq, tmp_path, full):
    """A real full file system (a small tmpfs in a private mount namespace) under --out or --cache-dir: one
    line naming the folder and "no space left", exit 2, no temporary left; with room the same command runs."""
    mount = tmp_path / "small"
    mount.mkdir()
    out = tmp_path / "run" if full == "cache" else mount / "run"
    cache = mount / "cache" if full == "cache" else tmp_path / "cache"
    fill = 'head -c 1m /dev/zero > "$0/fill" 2>/dev/null; ' if full == "zero" else ""  # 0 bytes free
    args = refine_args(seq, out, "--cache-dir", str(cache))
    script = ('mount -t tmpfs -o size=96k tmpfs "$0" && ' + fill + '"$@"; rc=$?; '
              'find "$0" -name ".tmp-*" | head -1 > "$0.left"; ls -A "$0" > "$0.top"; exit $rc')
    done = subprocess.run(["unshare", "-Urm", "sh", "-c", script, str(mount), sys.executable, "-m", "dm2_backend",
                           *args], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr[-2000:]
    line = last_line(done.stderr)
    assert line.startswith("dm2: error:") and "no space left" in line and str(mount) in line, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    assert Path(f"{mount}.left").read_text() == ""  # no temporary in the full folder
    if full != "cache":  # the run folder it created was removed
        assert Path(f"{mount}.top").read_text().split() == (["fill"] if full == "zero" else [])
    again = dm2(*refine_args(seq, tmp_path / "again", "--cache-dir", str(tmp_path / "cache2")))
    assert again.exit_code == 0, again.output


@pytest.mark.parametrize("where", ["out", "cache"])
def test_a_file_size_limit_is_one_line(seq, tmp_path, where):
    """The same through RLIMIT_FSIZE (any machine): the write that passes the limit fails with EFBIG."""
    out, cache = tmp_path / "run", tmp_path / "cache"
    limit = 48 << 10
    if where == "cache":  # the cache's frames entry is larger than the limit, the run's outputs are not written
        args = refine_args(seq, out, "--cache-dir", str(cache))
    else:
        args = refine_args(seq, out, "--no-cache")
    done = child(args, limits={resource.RLIMIT_FSIZE: limit})
    assert done.returncode == 2, done.stderr[-2000:]
    line = last_line(done.stderr)
    folder = str(cache) if where == "cache" else str(out)
    assert line.startswith("dm2: error:") and "file size limit" in line and folder in line, line
    assert "Traceback" not in done.stderr
    assert not list(tmp_path.rglob(".tmp-*"))
    assert not out.exists()  # the failed run removed the folder it created
    again = dm2(*args)
    assert again.exit_code == 0, again.output


# ------------------------------------------------------------------------------------ 5. tracebacks


def test_a_negative_seed_is_refused_before_the_preparation(seq, tmp_path):
    out = tmp_path / "run"
    one_line(dm2(*refine_args(seq, out, "--no-cache", "--seed", "-1")), "seed")
    assert not out.exists()


def test_a_bad_option_value_is_one_line_not_clicks_usage(seq, tmp_path):
    line = one_line(dm2(*refine_args(seq, tmp_path / "run", "--no-cache"), "--epochs", "1e9"), "--epochs", "1e9")
    assert "Usage" not in line


def test_a_huge_value_is_not_echoed_whole(seq, tmp_path):
    huge = "9" * (50 << 20) + "x"
    line = one_line(dm2(*refine_args(seq, tmp_path / "run", "--no-cache"), "--epochs", huge), "--epochs")
    assert len(line) < 2000


def test_resume_with_a_checkpoint_of_another_kind_of_run_is_one_line(seq, tmp_path):
    out = tmp_path / "run"
    assert dm2(*refine_args(seq, out, "--no-cache")).exit_code == 0
    state = torch.load(out / CHECKPOINT, weights_only=True)
    key, value = next((k, v) for k, v in state["model"].items() if torch.is_tensor(v) and v.ndim)
    state["model"][key] = torch.zeros((value.shape[0] + 3, *value.shape[1:]), dtype=value.dtype)
    torch.save(state, out / CHECKPOINT)
    one_line(dm2(*refine_args(seq, out, "--no-cache", "--resume")), CHECKPOINT, "another kind of run")
    assert (out / "report.json").exists() and not (out / LOCK).exists()


def test_a_symlink_loop_in_the_scan_folder_is_one_line(seq, tmp_path):
    scans = tmp_path / "scans"
    shutil.copytree(seq / "velodyne", scans)
    (scans / "999999.bin").symlink_to(scans / "999999.bin")
    args = refine_args(seq, tmp_path / "run", "--no-cache")
    args[args.index("--scans") + 1] = str(scans)
    for result in (dm2("info", str(scans)), dm2(*args)):
        one_line(result, "999999.bin", "symbolic links")


# ------------------------------------------------------------------ 6. signals, and issue 30 item 2


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP"])
def test_a_signal_during_optimisation_keeps_the_checkpoint_and_names_resume(seq, tmp_path, signame):
    out = tmp_path / "run"
    args = refine_args(seq, out, "--no-cache")
    args[args.index("--epochs") + 1] = "3"
    stopped = child(args, pattern=CHECKPOINT, signame=signame, nth=2)  # as the second checkpoint is written
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    line = last_line(stopped.stderr)
    assert line.startswith(f"dm2: interrupted ({signame})") and "--resume" in line and str(out) in line, line
    assert not (out / LOCK).exists()
    assert CHECKPOINT in json.loads((out / MARKER).read_text())["files"]
    resumed = dm2(*args, "--resume")
    assert resumed.exit_code == 0, resumed.output


def test_a_signal_during_the_dense_stage_resumes_it_where_it_stopped(tmp_path):
    """3D scans: SIGTERM as the dense stage keeps its second round; --resume continues after the first (the
    result equals an uninterrupted stage's: ``test_optim_dense``)."""
    sim = tmp_path / "sim"
    made = dm2("simulate", "-n", "24", "--beams", "16", "--columns", "360", "--seed", "2", "-o", str(sim), "-q")
    assert made.exit_code == 0, made.output
    out = tmp_path / "run"
    args = ["refine", "--scans", str(sim / "velodyne"), "--poses", str(sim / "warm_start.txt"), "--no-cache",
            "-q", "--out", str(out)]
    stopped = child(args, pattern=DENSE_CHECKPOINT, signame="SIGTERM", nth=2)
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    assert "--resume" in last_line(stopped.stderr) and not (out / "report.json").exists()
    assert DENSE_CHECKPOINT in json.loads((out / MARKER).read_text())["files"]
    resumed = dm2(*args, "--resume")
    assert resumed.exit_code == 0, resumed.output
    dense = json.loads((out / "report.json").read_text())["start"]["dense"]
    assert dense["resumed_after_round"] == 1 and dense["rounds"] > 1  # signalled as round 2 was being kept
    assert dense["depth_noise"] is None  # a LiDAR's cells are not weighed by range


def test_ctrl_c_during_preparation_leaves_a_folder_the_same_command_accepts(seq, tmp_path):
    """SIGINT as the first preparation step is cached: nothing of the run is kept, the line names the same
    command, and that command then runs (its finished steps from the cache)."""
    out, cache = tmp_path / "run", tmp_path / "cache"
    args = refine_args(seq, out, "--cache-dir", str(cache))
    stopped = child(args, pattern="*-*", signame="SIGINT", nth=1)
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    line = last_line(stopped.stderr)
    assert line.startswith("dm2: interrupted (Ctrl-C)") and "same command" in line and str(out) in line, line
    assert not out.exists()
    again = dm2(*args)
    assert again.exit_code == 0, again.output


def test_a_folder_holding_only_an_empty_marker_is_accepted(seq, tmp_path):
    """What a run killed (kill -9) in preparation leaves: a marker that lists nothing there."""
    out = tmp_path / "run"
    out.mkdir()
    (out / MARKER).write_text(json.dumps({"command": "refine", "fingerprint": {}, "files": []}))
    result = dm2(*refine_args(seq, out, "--no-cache"))
    assert result.exit_code == 0, result.output


# ---------------------------------------------------------------------------- 7. stale cache by content


def test_swapped_scans_with_their_mtimes_restored_change_the_cache_key(seq, tmp_path):
    scans = tmp_path / "scans"
    shutil.copytree(seq / "velodyne", scans)
    a, b = sorted(scans.glob("*.bin"))[:2]
    size = min(a.stat().st_size, b.stat().st_size)  # two scans of the same size (whole points, 16 bytes each)
    for p in (a, b):
        p.write_bytes(p.read_bytes()[:size])
    before = file_fingerprint(scans)
    times = {p: (p.stat().st_atime_ns, p.stat().st_mtime_ns) for p in (a, b)}
    data_a, data_b = a.read_bytes(), b.read_bytes()
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    for p, ns in times.items():
        os.utime(p, ns=ns)  # touch -r
    assert file_fingerprint(scans) != before
