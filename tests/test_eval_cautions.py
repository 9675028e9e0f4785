"""Cautions where a metric is ill-posed (issue 30, item 1): the rotation APE of a point-like path, the
"standing still" reference line, and index association refused when the counts differ."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.evaluation.cautions import principal_spread, rotation_caution, standing_still_rmse
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import RunInputs
from dm2_backend.pipeline.run_writer import evaluation_of


def _write_tum(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Path:
    xyz, q = se3.to_xyz_quat(poses, "xyzw")
    np.savetxt(path, np.c_[stamps, xyz, q], fmt="%.9f")
    return path


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def rotating_in_place(n: int = 300, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A hand-held camera that mostly rotates in place (positions within a few cm) and an estimate whose
    positions are off by about 7 cm and whose orientations are off by a few degrees."""
    rng = np.random.default_rng(seed)
    angles = np.c_[0.3 * np.sin(np.linspace(0, 6, n)), 0.2 * np.cos(np.linspace(0, 4, n)), np.linspace(0, 2, n)]
    xyz = rng.normal(0, 1, (n, 3)) * [0.025, 0.02, 0.015]
    gt = se3.from_xyz_euler(np.c_[xyz, angles])
    est = se3.from_xyz_euler(np.c_[xyz + rng.normal(0, 0.04, (n, 3)), angles + rng.normal(0, 0.03, (n, 3))])
    return gt, est


def test_a_point_like_path_cautions_on_the_rotation_and_shows_standing_still(tmp_path):
    gt, est = rotating_in_place()
    stamps = np.arange(len(gt)) * 0.1
    g, e = _write_tum(tmp_path / "gt.txt", stamps, gt), _write_tum(tmp_path / "est.txt", stamps, est)
    r = run("eval", g, e, "-a", "--json", tmp_path / "r.json")
    assert r.exit_code == 0, r.output
    assert "nearly a point" in r.output and "APE rotation" in r.output
    assert "standing still" in r.output
    entry = json.loads((tmp_path / "r.json").read_text())["estimates"][0]
    assert any("nearly a point" in c for c in entry["cautions"])
    spread = principal_spread(gt[:, :3, 3])
    assert entry["standing_still_ape_trans_rmse_m"] == pytest.approx(np.sqrt((spread ** 2).sum()))
    # at the origin no rotation is fitted: the rotation APE is what it says
    r = run("eval", g, e, "--align-origin")
    assert r.exit_code == 0 and "nearly a point" not in r.output


def test_a_path_that_moves_gets_no_caution(tmp_path):
    """A path spreading 10 m with 5 cm errors: the alignment determines the rotation and standing still is far."""
    rng = np.random.default_rng(2)
    n = 200
    t = np.linspace(0, 2 * np.pi, n)
    gt = se3.from_xyz_euler(np.c_[10 * np.cos(t), 6 * np.sin(t), 0.5 * np.sin(3 * t), 0 * t, 0 * t, t])
    est = se3.from_xyz_euler(se3.to_xyz_euler(gt) + np.c_[rng.normal(0, 0.05, (n, 3)), rng.normal(0, 0.01, (n, 3))])
    stamps = np.arange(n) * 0.1
    g, e = _write_tum(tmp_path / "gt.txt", stamps, gt), _write_tum(tmp_path / "est.txt", stamps, est)
    r = run("eval", g, e, "-a")
    assert r.exit_code == 0 and "caution" not in r.output


def test_point_like_is_relative_to_the_position_error():
    """The same 5 cm spread is a point for a 7 cm error and a path for a 5 mm error: no constant length."""
    positions = np.random.default_rng(3).normal(0, 1, (100, 3)) * [0.05, 0.04, 0.03]
    assert rotation_caution(positions, 0.07) is not None
    assert rotation_caution(positions, 0.005) is None
    assert rotation_caution(positions * 1000, 70.0) is not None  # scale-free: metres or millimetres alike


def test_standing_still_under_each_alignment():
    ref = np.array([[0.0, 0, 0], [2.0, 0, 0], [4.0, 0, 0]])
    assert standing_still_rmse(ref, "se3", False) == pytest.approx(np.sqrt(8 / 3))  # at the centroid
    assert standing_still_rmse(ref, "none", True) == pytest.approx(np.sqrt(20 / 3))  # at the first pose


def test_a_refine_report_carries_the_cautions():
    """The run's evaluation (report.json's ``cautions``, printed by refine and compare)."""
    gt, est = rotating_in_place()
    stamps = np.arange(len(gt)) * 0.1
    inputs = RunInputs(scans=None, given=None, given_format=None, given_path=None, gt=Trajectory(gt, stamps))
    metrics, cautions = evaluation_of(Trajectory(est, stamps), inputs)
    assert metrics["ape_rot_rmse_deg"] > 0
    assert any("nearly a point" in c for c in cautions) and any("standing still" in c for c in cautions)


def test_compare_prints_a_runs_cautions(tmp_path):
    run_dir = tmp_path / "a"
    run_dir.mkdir()
    (run_dir / "report.json").write_text(json.dumps({"method": "dm2 refine", "metrics": {"ape_trans_rmse_m": 0.069},
                                                     "cautions": ["standing still: scores 0.064 m"]}))
    r = run("compare", run_dir)
    assert r.exit_code == 0 and "a: caution: standing still: scores 0.064 m" in r.output


def test_index_association_with_different_counts_is_refused(tmp_path):
    """A TUM ground truth against KITTI-like poses without stamps: exit 2 naming --by-index; forced, it runs."""
    gt, est = rotating_in_place(50)
    g = _write_tum(tmp_path / "gt.txt", np.arange(50) * 0.01, gt)
    kitti = tmp_path / "est_kitti.txt"
    np.savetxt(kitti, est[:20, :3, :].reshape(20, 12))
    r = run("eval", g, kitti, "-a")
    assert r.exit_code == 2 and "--by-index" in r.output and "20 poses" in r.output
    assert "Traceback" not in r.output
    r = run("eval", g, kitti, "-a", "--by-index")
    assert r.exit_code == 0 and "only the first 20 poses" in r.output
