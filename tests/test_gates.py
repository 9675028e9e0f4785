"""The free-space gate of an alignment: scans of a box-shaped room taken from two places agree at their true
relative pose and contradict each other (walls where the other scan saw through) at a wrong one; each scan's
depth image is made once and kept with its cloud."""

from __future__ import annotations

import numpy as np
import pytest

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.gates import depth_image, free_space
from dm2_backend.kernel.geometry import se3

ROOM = np.array([[-10.0, -5.0, -1.5], [10.0, 5.0, 2.5]])  # box corners (m)


def scan_of_room(at: np.ndarray, planar: bool, n: int = 2000, seed: int = 0) -> np.ndarray:
    """Ray-cast returns of the room walls (and floor/ceiling in 3D) from ``at``, in the sensor frame."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.zeros(n) if planar else rng.uniform(-0.4, 0.3, n)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (ROOM[1] - at) / d, np.where(d < 0, (ROOM[0] - at) / d, np.inf))
    return d * t.min(1, keepdims=True)


@pytest.mark.parametrize("planar", [True, False])
def test_true_alignment_passes_and_a_wrong_one_sees_walls_in_free_space(planar):
    a_at, b_at = np.array([-3.0, 0.0, 0.0]), np.array([2.0, 1.0, 0.0])
    a = Cloud(scan_of_room(a_at, planar, seed=1), planar, 1.0)
    b = Cloud(scan_of_room(b_at, planar, seed=2), planar, 1.0)
    true = se3.from_xyz_euler(np.r_[b_at - a_at, 0, 0, 0])  # b's frame in a's frame (no rotation)
    wrong = se3.from_xyz_euler(np.r_[b_at - a_at + [4.0, -2.0, 0.0], 0, 0, 0])
    assert free_space(b, a, true, 0.3) < 0.02
    assert free_space(b, a, wrong, 0.3) > 0.2


def test_the_depth_image_is_made_once_and_gives_what_a_fresh_cloud_gives():
    pts = scan_of_room(np.zeros(3), planar=False, n=20000)
    cloud, fresh = Cloud(pts, False, 1.0), Cloud(pts, False, 1.0)
    image = depth_image(cloud, 360)
    assert depth_image(cloud, 360) is image
    T = se3.from_xyz_euler(np.r_[0.5, 0.2, 0.0, 0.0, 0.0, 0.1])
    for _ in range(2):  # the second call uses the kept image
        assert free_space(Cloud(pts, False, 1.0), cloud, T, 0.3) == free_space(Cloud(pts, False, 1.0), fresh, T, 0.3)
    assert np.isfinite(image.depth).mean() > 0.5 and (image.near <= image.depth).all()


def test_a_failed_gate_is_a_code_with_its_message():
    """The reason a registration is refused is a :class:`Gate` with the value and limit; its text is the
    report's (``fitness 0.20 < 0.50``), so the run folders read as before."""
    from dm2_backend.algorithms.gates import Gate, GateFailure

    assert str(GateFailure(Gate.FITNESS, 0.2, 0.5)) == "fitness 0.20 < 0.50"
    assert str(GateFailure(Gate.RMSE, 0.1234, 0.1)) == "rmse 0.123 > 0.100"
    assert Gate.FREE_SPACE.message(0.31, 0.25) == "free space 0.31 > 0.25"
