"""No silent substitutions (issue 30, item 3): a warm start that cannot run, --gt with --graph, conversions
that invent or drop timestamps, repeated stamps written to formats without stamps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from shared_helpers import one_line_error, run

from dm2_backend.formats import read_trajectory
from dm2_backend.formats.g2o import write_g2o
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph


def loop(n: int = 30) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return se3.from_xyz_euler(np.c_[5 * np.cos(a), 3 * np.sin(a), 0.2 * np.sin(2 * a), 0 * a, 0 * a, a])


def write_tum(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Path:
    xyz, q = se3.to_xyz_quat(poses, "xyzw")
    np.savetxt(path, np.c_[stamps, xyz, q], fmt="%.9f")
    return path


def test_warm_start_poses_without_poses_is_an_error(tmp_path):
    scans = tmp_path / "velodyne"
    scans.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        rng.normal(0, 5, (200, 4)).astype(np.float32).tofile(scans / f"{i:06d}.bin")
    r = run("refine", "--scans", scans, "--warm-start", "poses", "--out", tmp_path / "run")
    one_line_error(r, "--warm-start poses", "--poses")
    assert not (tmp_path / "run").exists()  # refused before any work
    cfg = tmp_path / "c.yaml"
    cfg.write_text("warm_start: {name: poses}\n")
    r = run("refine", "--scans", scans, "-c", cfg, "--out", tmp_path / "run")
    one_line_error(r, str(cfg), "--poses")


def test_gt_with_graph_is_evaluated(tmp_path):
    gt = loop()
    n = len(gt)
    edges = np.array([(i, (i + 1) % n) for i in range(n)] + [(0, n // 2)])
    rel = se3.relative(gt[edges[:, 0]], gt[edges[:, 1]])
    drift = gt.copy()
    drift[:, :3, 3] += 0.05 * np.arange(n)[:, None] * [1.0, 0.5, 0.0]  # the initial vertices drift
    info = np.tile(np.eye(6) * 100.0, (len(edges), 1, 1))
    write_g2o(PoseGraph(np.arange(n), drift, edges, rel, info, planar=False), tmp_path / "g.g2o")
    kitti = tmp_path / "gt.txt"
    np.savetxt(kitti, gt[:, :3, :].reshape(n, 12))
    r = run("baseline", "gtsam", "--graph", tmp_path / "g.g2o", "--gt", kitti, "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["metrics"]["ape_trans_rmse_m"] < 1e-3 < report["initial_metrics"]["ape_trans_rmse_m"]
    assert "ape_trans_rmse_m" in r.output
    np.savetxt(kitti, gt[:-1, :3, :].reshape(n - 1, 12))
    r = run("baseline", "gtsam", "--graph", tmp_path / "g.g2o", "--gt", kitti, "-o", tmp_path / "out2")
    one_line_error(r, "29 ground-truth poses for the 30 vertices")
    r = run("baseline", "gtsam", "--graph", tmp_path / "g.g2o", "--poses", kitti, "-o", tmp_path / "out3")
    assert r.exit_code == 2 and "--poses: not used with --graph" in r.output


def test_conversions_say_when_stamps_are_invented_and_times_supplies_them(tmp_path):
    poses = loop()
    kitti = tmp_path / "poses.kitti"
    np.savetxt(kitti, poses[:, :3, :].reshape(len(poses), 12))
    r = run("convert", kitti, tmp_path / "a.tum")
    assert r.exit_code == 0 and "has no timestamps" in r.output and "--times" in r.output
    times = tmp_path / "stamps.txt"
    stamps = 1e9 + 0.1 * np.arange(len(poses))
    times.write_text("".join(f"{float(t)!r}\n" for t in stamps))
    r = run("convert", kitti, tmp_path / "b.tum", "--times", times)
    assert r.exit_code == 0 and "no timestamps" not in r.output
    np.testing.assert_array_equal(read_trajectory(tmp_path / "b.tum").timestamps, stamps)
    # a g2o graph has no stamps either: --times gives them
    r = run("convert", kitti, tmp_path / "c.g2o")
    r = run("convert", tmp_path / "c.g2o", tmp_path / "c.tum", "--times", times)
    assert r.exit_code == 0 and "no timestamps" not in r.output
    np.testing.assert_array_equal(read_trajectory(tmp_path / "c.tum").timestamps, stamps)


def test_conversions_say_when_stamps_are_dropped(tmp_path):
    poses = loop()
    stamps = 100.0 + 0.1 * np.arange(len(poses))
    tum = write_tum(tmp_path / "t.txt", stamps, poses)
    r = run("convert", tum, tmp_path / "a.kitti")
    assert r.exit_code == 0 and "stores no timestamps" in r.output and "--out-times" in r.output
    r = run("convert", tum, tmp_path / "a.g2o")
    assert r.exit_code == 0 and "stores no timestamps" in r.output
    r = run("convert", tum, tmp_path / "b.kitti", "--out-times", tmp_path / "times.txt")
    assert r.exit_code == 0 and "stores no timestamps" not in r.output
    back = read_trajectory(tmp_path / "b.kitti", "kitti", None)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "times.txt"), stamps)
    assert len(back) == len(poses)


@pytest.mark.parametrize("suffix", ["kitti", "g2o"])
def test_repeated_stamps_are_no_obstacle_for_formats_without_stamps(tmp_path, suffix):
    poses = loop()
    stamps = 100.0 + 0.1 * np.arange(len(poses))
    stamps[5] = stamps[4]  # a repeated stamp, as in TUM fr2_desk's ground truth
    tum = write_tum(tmp_path / "t.txt", stamps, poses)
    r = run("convert", tum, tmp_path / f"out.{suffix}")
    assert r.exit_code == 0, r.output
    assert len(read_trajectory(tmp_path / f"out.{suffix}")) == len(poses)  # every pose kept
