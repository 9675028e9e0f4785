"""The "paper ATE" equals the DeepMapping2 official compute_ate (re-derived here independently)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dm2_backend.evaluation.paper_ate import paper_ate
from dm2_backend.kernel.geometry import se3

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "trajectories"


def official_style(est6: np.ndarray, gt6: np.ndarray) -> tuple[float, float]:
    """ai4ce/DeepMapping2 utils/geometry_utils.py compute_ate (euler_angle representation), step by step:
    Kabsch of est -> gt positions with the reflection fix, yaw + alignment yaw, loop wraps, fold, and
    sqrt(mean distance), mean |yaw| in degrees."""
    a, b = est6[:, :3], gt6[:, :3]
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    R = vt.T @ u.T
    if np.linalg.det(R) < 0:
        vt[2, :] *= -1
        R = vt.T @ u.T
    t = cb - R @ ca
    aligned = a @ R.T + t
    yaw = est6[:, 5] + Rotation.from_matrix(R).as_euler("XYZ")[2]
    yaw_gt = gt6[:, 5].copy()
    for y in (yaw, yaw_gt):
        while np.any(y > np.pi):
            y[y > np.pi] -= 2 * np.pi
        while np.any(y < -np.pi):
            y[y < -np.pi] += 2 * np.pi
    rot = np.abs(yaw - yaw_gt)
    rot[rot > np.pi] = 2 * np.pi - rot[rot > np.pi]
    return float(np.sqrt(np.mean(np.linalg.norm(aligned - b, axis=1)))), float(np.mean(rot) * 180 / np.pi)


def test_matches_official_definition_on_random_3d():
    rng = np.random.default_rng(0)
    gt = se3.from_xyz_euler(np.c_[rng.normal(0, 20, (200, 3)), rng.uniform(-3, 3, (200, 3))])
    est = se3.from_xyz_euler(se3.to_xyz_euler(gt) + rng.normal(0, 0.3, (200, 6)))
    est = se3.make_poses(se3.euler_xyz_to_matrix([0.1, -0.2, 2.5]), [5, -3, 1]) @ est
    res = paper_ate(gt, est)
    ref_t, ref_r = official_style(se3.to_xyz_euler(est), se3.to_xyz_euler(gt))
    assert res.trans == pytest.approx(ref_t, abs=1e-9) and res.rot_deg == pytest.approx(ref_r, abs=1e-9)


def test_matches_official_definition_on_kitti():
    if not DATA.is_dir():
        pytest.skip(f"shared data absent ({DATA})")
    from evo.tools import file_interface

    gt = np.array(file_interface.read_kitti_poses_file(str(DATA / "KITTI_00_gt.txt")).poses_se3)
    est = np.array(file_interface.read_kitti_poses_file(str(DATA / "KITTI_00_ORB.txt")).poses_se3)
    res = paper_ate(gt, est)
    ref_t, ref_r = official_style(se3.to_xyz_euler(est), se3.to_xyz_euler(gt))
    assert res.trans == pytest.approx(ref_t, abs=1e-9) and res.rot_deg == pytest.approx(ref_r, abs=1e-9)
    # sqrt of the MEAN DISTANCE: not the RMSE
    assert res.trans == pytest.approx(np.sqrt(res.trans_errors.mean()))
    assert res.trans != pytest.approx(np.sqrt(np.mean(res.trans_errors**2)), rel=1e-3)


def test_zero_for_a_rigidly_moved_planar_copy():
    rng = np.random.default_rng(1)
    gt = se3.from_xy_yaw(np.c_[np.cumsum(rng.normal(0, 1, (100, 2)), 0), rng.uniform(-np.pi, np.pi, 100)])
    est = se3.from_xy_yaw(np.array([3.0, -2.0, 2.9])) @ gt
    res = paper_ate(gt, est)
    assert res.trans < 1e-6 and res.rot_deg < 1e-9


def test_needs_three_pairs():
    with pytest.raises(ValueError):
        paper_ate(se3.identity(2), se3.identity(2))
