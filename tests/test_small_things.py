"""The small things of issue 30 (item 5): --max-diff named, `dm2 info RUN_FOLDER`, did-you-mean, the epoch
plot's returned epoch, the demo's temporary folder, a run's total time, a malformed g2o's one line."""

from __future__ import annotations

import getpass
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.evaluation import plots
from dm2_backend.formats.g2o import write_g2o
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph


def run(*args, obj=None):
    return CliRunner().invoke(cli, [str(a) for a in args], obj={} if obj is None else obj)


def one_line_error(r, *needles: str) -> str:
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.strip().splitlines() if line]
    assert len(lines) == 1 and "Traceback" not in r.output and "Warning" not in r.output, r.output
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def scan_folder(root: Path, n: int = 4) -> Path:
    scans = root / "velodyne"
    scans.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        rng.normal(0, 5, (200, 4)).astype(np.float32).tofile(scans / f"{i:06d}.bin")
    (root / "times.txt").write_text("".join(f"{0.1 * i!r}\n" for i in range(n)))
    return scans


def small_graph(path: Path) -> Path:
    n = 8
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    gt = se3.from_xy_yaw(np.c_[4 * np.cos(a), 4 * np.sin(a), a + np.pi / 2])
    edges = np.array([(i, (i + 1) % n) for i in range(n)])
    rel = se3.relative(gt[edges[:, 0]], gt[edges[:, 1]])
    info = np.tile(np.diag([10.0, 10.0, 50.0]), (n, 1, 1))
    write_g2o(PoseGraph(np.arange(n), gt, edges, rel, info, planar=True), path)
    return path


def test_scans_without_a_pose_name_max_diff(tmp_path):
    scans = scan_folder(tmp_path)
    poses = tmp_path / "poses.txt"
    poses.write_text("".join(f"{0.1 * i!r} 0 0 0 0 0 0 1\n" for i in range(3)))  # no pose for the 4th scan
    r = run("refine", "--scans", scans, "--poses", poses, "--out", tmp_path / "run")
    one_line_error(r, "only 3 of 4 scans have a pose within 0.01 s", "--max-diff")


def test_info_of_a_run_folder(tmp_path):
    r = run("baseline", "gtsam", "--graph", small_graph(tmp_path / "g.g2o"), "-o", tmp_path / "run")
    assert r.exit_code == 0, r.output
    r = run("info", tmp_path / "run")
    assert r.exit_code == 0, r.output
    assert "dm2 run folder" in r.output and "method" in r.output and "poses_kitti.txt" in r.output


def test_did_you_mean(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("optimiser:\n  epoch: 3\n")
    scans = scan_folder(tmp_path)
    r = run("refine", "--scans", scans, "-c", cfg, "--out", tmp_path / "run")
    one_line_error(r, str(cfg), "epoch", "did you mean 'epochs'?")
    cfg.write_text("optimizer: {}\n")
    r = run("refine", "--scans", scans, "-c", cfg, "--out", tmp_path / "run")
    one_line_error(r, "did you mean 'optimiser'?")
    r = run("evl")
    assert r.exit_code == 2 and "did you mean 'eval'?" in r.output


def test_epoch_plot_names_the_returned_epoch():
    records = [{"epoch": i, "ate": v, "ate_metric": "ape_trans_rmse_m"} for i, v in enumerate([0.5, 0.3, 0.45])]
    report = {"epochs": records, "start_metrics": {"ape_trans_rmse_m": 0.6}, "best_epoch": 1}
    fig = plots.epochs_figure(records, plots.run_start(report), report["best_epoch"])
    title = fig.axes[0].get_title()
    assert "epoch 2 (returned) 0.3" in title and "-50.0 %" in title  # not the last epoch's 0.45
    start_kept = plots.epochs_figure(records, plots.run_start(report), -1).axes[0].get_title()
    assert "start (returned) 0.6" in start_kept


def test_the_demo_leaves_one_folder_in_the_temporary_directory(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    for _ in range(2):
        r = run("demo", "--frames", "40", "--epochs", "1", "-q")
        assert r.exit_code == 0, r.output
    demos = [p.name for p in tmp_path.iterdir() if p.name.startswith("dm2-demo")]
    assert demos == [f"dm2-demo-{getpass.getuser()}"]  # the second demo replaced the first
    marker = tmp_path / demos[0] / ".dm2-run.json"  # as an earlier dm2 wrote it: no identities
    doc = json.loads(marker.read_text())
    del doc["identity"]
    marker.write_text(json.dumps(doc))
    r = run("demo", "--frames", "40", "--epochs", "1", "-q")
    assert r.exit_code == 0, r.output  # the demo's own folder: its earlier files are replaced all the same


def test_a_runs_total_counts_the_whole_command(tmp_path):
    """The report's total runs from the command's start (here an hour ago), not from the solver's."""
    started = time.perf_counter() - 3600.0
    r = run("baseline", "gtsam", "--graph", small_graph(tmp_path / "g.g2o"), "-o", tmp_path / "run",
            obj={"started": started})
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "run" / "report.json").read_text())["timings"]["total"] >= 3600.0


@pytest.mark.parametrize("text", ["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1e200 0 0 1e200 0 0 1\n",
                                  "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1e308 1e308 0\n"
                                  "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
                                  "EDGE_SE3:QUAT 0 1 1e308 0 0 0 0 0 1" + " 1" * 21 + "\n"
                                  "EDGE_SE3:QUAT 1 2 1e308 0 0 0 0 0 1" + " 1" * 21 + "\n"])
@pytest.mark.filterwarnings("error::RuntimeWarning")  # numpy's overflow warnings around the line: none
def test_a_malformed_g2o_is_one_line_before_any_solver(tmp_path, text):
    path = tmp_path / "huge.g2o"
    path.write_text(text)
    r = run("baseline", "gtsam", "--graph", path, "-o", tmp_path / "run")
    one_line_error(r, "huge.g2o")
    assert "poses_kitti" not in r.output  # refused when read, not when the result is written


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_kitti_poses_with_huge_rotation_entries_are_one_line(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1e200 0 0 0 0 1e200 0 0 0 0 1 0\n")
    one_line_error(run("info", path, "--format", "kitti"), "poses.txt", "not a rotation")
