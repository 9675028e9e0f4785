"""2D point-to-line ICP: the robust (Cauchy-reweighted) steps against plain least squares."""

from __future__ import annotations

import numpy as np
import pytest

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.icp import icp_2d
from dm2_backend.kernel.geometry import se3


def _room(rng: np.random.Generator, spacing: float = 0.05, noise: float = 0.01) -> np.ndarray:
    """Points on the four walls of a 12 m x 6 m room (x, y, z = 0) with range noise."""
    xs, ys = np.arange(-6, 6, spacing), np.arange(-3, 3, spacing)
    walls = [np.c_[xs, np.full_like(xs, -3)], np.c_[xs, np.full_like(xs, 3)],
             np.c_[np.full_like(ys, -6), ys], np.c_[np.full_like(ys, 6), ys]]
    xy = np.vstack(walls)
    return np.c_[xy + rng.normal(0, noise, xy.shape), np.zeros(len(xy))]


@pytest.fixture
def scans() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target scan, source scan 0.4 m further along x, and the true pose of the source in the target."""
    rng = np.random.default_rng(3)
    truth = se3.from_xy_yaw(np.array([0.4, 0.0, 0.0]))
    target = _room(rng)
    source_world = _room(rng)
    # a surface only the source sees, 0.3 m in front of the far wall (a parked car that left), within
    # the correspondence distance of that wall's points
    ghost_y = np.arange(-2.5, 2.5, 0.05)
    ghost = np.c_[np.full_like(ghost_y, 5.7), ghost_y, np.zeros_like(ghost_y)]
    source_world = np.vstack([source_world, ghost])
    source = se3.transform_points(se3.inverse(truth), source_world)
    return target, source, truth


def _error(T: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(se3.relative(truth, T)[:2, 3]))


def test_robust_steps_ignore_a_surface_one_scan_sees(scans):
    target, source, truth = scans
    tgt = Cloud(target, True, 0.5).ensure("point-to-plane")
    init = se3.from_xy_yaw(np.array([0.3, 0.05, 0.01]))
    plain = icp_2d(source[:, :2], tgt, init, (0.5,))
    robust = icp_2d(source[:, :2], tgt, init, (0.5,), robust_k=2.3849)
    # least squares splits the difference between the wall and the surface 0.3 m in front of it
    assert _error(plain.T, truth) > 0.05
    assert _error(robust.T, truth) < 0.01  # Cauchy weights redescend slowly: the 100 points still pull a little
    assert abs(se3.to_xy_yaw(se3.relative(truth, robust.T))[2]) < np.radians(0.05)


def test_robust_steps_keep_a_clean_match(scans):
    target, source, truth = scans
    clean = source[: len(target)]  # the room alone
    tgt = Cloud(target, True, 0.5).ensure("point-to-plane")
    init = se3.from_xy_yaw(np.array([0.2, -0.1, -0.02]))
    plain = icp_2d(clean[:, :2], tgt, init, (1.0, 0.5))
    robust = icp_2d(clean[:, :2], tgt, init, (1.0, 0.5), robust_k=2.3849)
    assert _error(plain.T, truth) < 0.005
    assert _error(robust.T, truth) < 0.005
