"""Scan matches weighed against the odometry by their own match cycles (:mod:`dm2_backend.algorithms.match_noise`,
``weigh: cycles``): sharp scans over a slipping odometry are taken whole, noisy scans over a precise odometry lean on
it, and the fused warm start then keeps what the precise odometry got right."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import FLOOR, WAYPOINTS_2D, box_mesh, frames_from, polyline_path

from dm2_backend.algorithms.common import fine_distance
from dm2_backend.algorithms.match_noise import MatchWeights, match_weights
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.simulate.lidar import LidarModel, Raycaster


def scans_along(truth: np.ndarray, range_noise: float, seed: int = 0):
    model = LidarModel(planar=True, columns=360, max_range=8.0, range_noise=range_noise, dropout=0.02, height=1.0)
    caster = Raycaster(box_mesh(FLOOR), model)
    rng = np.random.default_rng(seed)
    return frames_from([caster.scan(T, rng) * np.array([1, 1, 0], np.float32) for T in truth], planar=True)


def odometry_of(truth: np.ndarray, sigma_t: float, sigma_yaw: float, seed: int = 1) -> np.ndarray:
    """The true increments, each perturbed by white noise (a random walk in the poses)."""
    rng = np.random.default_rng(seed)
    steps = se3.relative(truth[:-1], truth[1:])
    noise = se3.from_xy_yaw(np.column_stack([rng.normal(0, sigma_t, (len(steps), 2)),
                                             rng.normal(0, sigma_yaw, len(steps))]))
    out = [truth[0]]
    for s, e in zip(steps, noise, strict=True):
        out.append(out[-1] @ s @ e)
    return np.array(out)


def rpe(poses: np.ndarray, truth: np.ndarray) -> float:
    d = se3.relative(se3.relative(truth[:-1], truth[1:]), se3.relative(poses[:-1], poses[1:]))
    return float(np.sqrt(np.mean(np.sum(d[:, :2, 3] ** 2, axis=1))))


@pytest.fixture(scope="module")
def truth():
    return polyline_path(WAYPOINTS_2D, 0.4)


def test_sharp_scans_over_a_slipping_odometry_are_taken_whole(truth):
    frames = scans_along(truth, 0.005)
    odometry = odometry_of(truth, 0.03, np.radians(1.0))
    w = match_weights(frames.points, odometry, fine_distance(frames.scale))
    assert w.triples >= 20
    assert min(w.weights) > 0.8, w
    # the cycles close far more tightly than the matches agree with the odometry
    assert all(c < 0.5 * d for c, d in zip(w.cycle_spread, w.disagreement_spread, strict=True))
    # by default (weigh: auto) such matches are taken whole: the same poses as weigh: whole, the weights reported
    auto = IcpWarmStart(progress=False)
    poses = auto.run(frames, Trajectory(odometry))
    np.testing.assert_array_equal(poses, IcpWarmStart(weigh="whole", progress=False).run(frames, Trajectory(odometry)))
    assert auto.report["match_weights"]["weighed"] == "whole"
    assert auto.report["match_weights"]["weights"] == [round(x, 6) for x in w.weights]
    assert "scan matches taken whole" in auto.report["summary"]


def test_noisy_scans_over_a_precise_odometry_lean_on_it(truth):
    frames = scans_along(truth, 0.12)
    odometry = odometry_of(truth, 0.0005, np.radians(0.01))
    w = match_weights(frames.points, odometry, fine_distance(frames.scale))
    assert max(w.weights) < 0.5, w
    ws = IcpWarmStart(weigh="cycles", progress=False)
    poses = ws.run(frames, Trajectory(odometry))
    whole = IcpWarmStart(weigh="whole", progress=False).run(frames, Trajectory(odometry))
    # the weighed warm start keeps (nearly) what the odometry got right step by step; taken whole it does not
    assert rpe(poses, truth) < 0.5 * rpe(whole, truth)
    assert rpe(poses, truth) < rpe(odometry, truth) + 0.01
    assert ws.report["match_weights"]["weights"] == [round(x, 6) for x in ws._weights.weights]
    assert "scan matches weighed" in ws.report["summary"]
    # by default (weigh: auto) the cycles weigh such matches
    np.testing.assert_array_equal(IcpWarmStart(progress=False).run(frames, Trajectory(odometry)), poses)


def test_blend_and_no_evidence():
    w = MatchWeights((0.5, 0.0, 1.0), (0.1,) * 3, (0.2,) * 3, 30)
    predicted = se3.from_xy_yaw(np.array([1.0, 2.0, 0.3]))
    match = predicted @ se3.from_xy_yaw(np.array([0.2, 0.4, 0.1]))
    got = se3.to_xy_yaw(se3.relative(predicted, w.blend(predicted, match)))
    np.testing.assert_allclose(got, [0.1, 0.0, 0.1], atol=1e-12)
    two = match_weights([np.zeros((5, 3))] * 2, np.tile(np.eye(4), (2, 1, 1)), 0.1)
    assert two.weights == (1.0, 1.0, 1.0) and two.more_precise == "scan"
    with pytest.raises(Exception, match="weigh"):
        IcpWarmStart(weigh="maybe", progress=False).run(scans_along(polyline_path(WAYPOINTS_2D, 2.0)[:5], 0.01),
                                                         Trajectory(polyline_path(WAYPOINTS_2D, 2.0)[:5]))
