"""Warm-start plugins on synthetic scenes: icp removes the drift of a noisy odometry; poses/kiss errors."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import floor_2d, room_3d

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.plugins.warm_start_kiss import KissWarmStart
from dm2_backend.plugins.warm_start_poses import PosesWarmStart
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.path import drifting_odometry


@pytest.fixture(scope="module")
def floor():
    return floor_2d()


def rmse(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))


def step_errors(poses: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = se3.relative(se3.relative(truth[:-1], truth[1:]), se3.relative(poses[:-1], poses[1:]))
    return np.linalg.norm(e[:, :3, 3], axis=1), np.degrees(se3.rotation_angle(e[:, :3, :3]))


def test_icp_removes_odometry_drift_2d(floor):
    frames, truth = floor
    noisy = drifting_odometry(truth, 1, 0.01, 0.05, 0.004)
    poses = IcpWarmStart(progress=False).run(frames, Trajectory(noisy))
    assert poses.shape == truth.shape and se3.is_planar(poses)
    np.testing.assert_allclose(poses[0], noisy[0])  # starts where the given trajectory starts
    assert rmse(noisy, truth) > 5.0
    assert rmse(poses, truth) < 0.5  # the featureless corridor keeps some of the odometry's error
    et, er = step_errors(poses, truth)
    assert np.median(et) < 0.01 and np.median(er) < 0.1


def test_icp_constant_velocity_without_odometry(floor):
    frames, truth = floor
    poses = IcpWarmStart(prior="velocity", progress=False).run(frames, None)
    aligned = truth[0] @ poses  # no given trajectory: starts at the identity
    assert rmse(aligned, truth) < 1.0
    et, er = step_errors(poses, truth)
    assert np.percentile(et, 95) < 0.05 and np.percentile(er, 95) < 0.5


def test_icp_point_to_point_variant(floor):
    frames, truth = floor
    n = 50  # room A only
    sub = type(frames)(frames.points[:n], None, True, frames.scale)
    noisy = drifting_odometry(truth[:n], 2, 0.01, 0.05, 0.004)
    poses = IcpWarmStart(method="point-to-point", progress=False).run(sub, Trajectory(noisy))
    assert rmse(poses, truth[:n]) < 0.5 * rmse(noisy, truth[:n])
    assert rmse(poses, truth[:n]) < 0.1


def test_icp_3d_room():
    frames, truth = room_3d(count=30)
    noisy = drifting_odometry(truth, 3, 0.01, 0.05, 0.01)
    poses = IcpWarmStart(progress=False).run(frames, Trajectory(noisy))
    assert rmse(poses, truth) < 0.5 * rmse(noisy, truth)
    assert rmse(poses, truth) < 0.1
    et, er = step_errors(poses, truth)
    assert et.max() < 0.05 and er.max() < 0.5


def test_icp_3d_constant_velocity_stays_rigid():
    # chained ICP results and velocities used to lose rigidity after some 40 frames and then diverge
    frames, truth = room_3d(count=50)
    poses = IcpWarmStart(prior="velocity", progress=False).run(frames, None)
    assert se3.rotation_error(poses[:, :3, :3]).max() < 1e-9
    et, er = step_errors(poses, truth)
    assert et.max() < 0.05 and er.max() < 0.5


def test_icp_options_checked(floor):
    frames, truth = floor
    with pytest.raises(InputError, match="prior"):
        IcpWarmStart(prior="psychic").run(frames, None)
    with pytest.raises(InputError, match="needs a trajectory"):
        IcpWarmStart(prior="given").run(frames, None)
    with pytest.raises(InputError, match="poses for"):
        IcpWarmStart(prior="given").run(frames, Trajectory(truth[:5]))
    with pytest.raises(InputError, match="ICP method"):
        IcpWarmStart(method="magic").run(frames, None)


def test_poses_warm_start(floor):
    frames, truth = floor
    out = PosesWarmStart().run(frames, Trajectory(truth))
    np.testing.assert_allclose(out, truth, atol=1e-12)
    with pytest.raises(InputError, match="needs a trajectory"):
        PosesWarmStart().run(frames, None)
    with pytest.raises(InputError, match="poses for"):
        PosesWarmStart().run(frames, Trajectory(truth[:3]))


def test_kiss_icp_optional(floor):
    frames, _ = floor
    try:
        import kiss_icp  # noqa: F401
    except ImportError:
        with pytest.raises(InputError, match=r"install dm2\[kiss\]"):
            KissWarmStart().run(frames, None)
        return
    frames3, truth3 = room_3d(count=60)  # KISS-ICP expects small motions between frames
    poses = KissWarmStart(progress=False).run(frames3, Trajectory(truth3))
    assert rmse(poses, truth3) < 0.1
