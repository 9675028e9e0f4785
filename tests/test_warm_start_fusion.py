"""The icp warm start with odometry (planar): per-step degeneracy test and fallback, on hard cases built
from the simulator: a ring of long featureless corridors, a stretch of broken scans, odometry glitches."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import floor_2d, frames_from

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.icp import information_2d, slide_loss
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart, StepReason
from dm2_backend.simulate.corridor import corridor_sequence
from dm2_backend.simulate.path import drifting_odometry


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))


@pytest.fixture(scope="module")
def corridor():
    scans, truth, odometry = corridor_sequence()
    return scans, frames_from(scans, planar=True), truth, odometry


def test_degeneracy_measures_see_a_corridor():
    x = np.arange(-6, 6, 0.03)
    walls = np.concatenate([np.column_stack([x, np.full_like(x, -1.0)]), np.column_stack([x, np.full_like(x, 1.0)])])
    target = Cloud(np.column_stack([walls, np.zeros(len(walls))]), True, 0.1)
    scan = walls[np.abs(walls[:, 0]) < 3]
    info = information_2d(scan, target, np.eye(4), 0.1)
    assert info["fitness"] > 0.99 and info["weak"] < 0.02
    assert abs(info["weak_axis"][0]) > 0.99  # the weak direction runs along the corridor
    assert slide_loss(scan, target, np.eye(4), np.array([0.1, 0.0, 0.0]), 0.1) < 0.05
    assert slide_loss(scan, target, np.eye(4), np.array([0.0, 0.1, 0.0]), 0.1) > 0.5  # across: pinned
    # an end wall pins the along-corridor direction too
    end = np.column_stack([np.full(60, 3.0), np.linspace(-1, 1, 60)])
    closed = np.concatenate([scan, end])
    target2 = Cloud(np.column_stack([np.concatenate([walls, end]), np.zeros(len(walls) + 60)]), True, 0.1)
    assert information_2d(closed, target2, np.eye(4), 0.1)["weak"] > 0.05
    assert slide_loss(closed, target2, np.eye(4), np.array([0.1, 0.0, 0.0]), 0.1) > 0.05


def test_corridor_ring_never_worse_than_odometry(corridor):
    _, frames, truth, odometry = corridor
    ws = IcpWarmStart(fuse="auto", progress=False)
    poses = ws.run(frames, Trajectory(odometry))
    assert ate(odometry, truth) > 3.0
    assert ate(poses, truth) < 0.1 * ate(odometry, truth) and ate(poses, truth) < 0.3
    rep = ws.report
    assert rep["fused"] and rep["steps"] == len(truth) - 1 == sum(rep["sources"].values())
    assert rep["match_weights"]["weighed"] == "whole"  # the cycles do not find this odometry the more precise
    assert rep["summary"].startswith(f"icp warm start: {rep['sources']['scan']} of {rep['steps']} steps")
    assert len(rep["per_step"]["source"]) == len(truth)
    # the straight stretches far from the corners and niches are flagged degenerate along the corridor
    src = np.array(rep["per_step"]["source"])
    assert rep["sources"]["scan across, odometry along"] > 0.3 * rep["steps"]
    partial = src == "scan across, odometry along"
    heading = se3.to_xy_yaw(truth)[:, 2]
    along_x = np.abs(np.sin(heading[partial])) < 0.2
    along_y = np.abs(np.cos(heading[partial])) < 0.2
    assert (along_x | along_y).mean() > 0.95  # flagged only while driving along a corridor


def test_broken_stretch_falls_back_to_odometry(corridor):
    """50 consecutive scans reduced to 5 points each (a blinded laser): the odometry carries the stretch."""
    scans, _, truth, odometry = corridor
    broken = [s[:5] if 200 <= i < 250 else s for i, s in enumerate(scans)]
    frames = frames_from(broken, planar=True)
    ws = IcpWarmStart(fuse="auto", progress=False)
    poses = ws.run(frames, Trajectory(odometry))
    src = np.array(ws.report["per_step"]["source"])
    assert (src[200:250] == "odometry").mean() > 0.9
    assert all("overlap" in r or "degenerate" in r for r in np.array(ws.report["per_step"]["reason"])[200:250])
    assert ate(poses, truth) < 0.2 * ate(odometry, truth)
    # across the stretch the warm start is no worse than the odometry's own increments there
    e_ws = np.linalg.norm(se3.relative(poses[199], poses[250])[:2, 3] - se3.relative(truth[199], truth[250])[:2, 3])
    e_odo = np.linalg.norm(se3.relative(odometry[199], odometry[250])[:2, 3]
                           - se3.relative(truth[199], truth[250])[:2, 3])
    assert e_ws < e_odo + 0.1


def test_odometry_glitches_are_overruled_by_the_scans():
    frames, truth = floor_2d()
    odometry = drifting_odometry(truth, 1, 0.002, 0.02, 0.001)
    glitch = se3.from_xy_yaw(np.array([[0.4, -0.3, 0.15]]))[0]
    for k in (40, 90, 130):  # a wheel slip: every later pose jumps
        odometry[k:] = odometry[k - 1] @ glitch @ se3.relative(odometry[k - 1], odometry[k:])
    ws = IcpWarmStart(fuse="auto", progress=False)
    poses = ws.run(frames, Trajectory(odometry))
    reasons = ws.report["per_step"]["reason"]
    assert all(reasons[k].startswith("odometry glitch") for k in (40, 90, 130))
    assert ate(poses, truth) < 0.3 < ate(odometry, truth)
    # counted by reason code, not by message: every kind is a code's label, and the glitches are among them
    labels = {r.value for r in StepReason}
    assert set(ws.report["reasons"]) <= labels and ws.report["reasons"][StepReason.GLITCH.value] >= 3


def test_fusion_options_checked(corridor):
    from dm2_backend.runtime.errors import InputError

    _, frames, _, odometry = corridor
    with pytest.raises(InputError, match="fuse"):
        IcpWarmStart(fuse="maybe", progress=False).run(frames, Trajectory(odometry))
    with pytest.raises(InputError, match="min_constraint"):
        IcpWarmStart(fuse="auto", min_constraint=0.7, progress=False).run(frames, Trajectory(odometry))
    plain = IcpWarmStart(fuse="off", progress=False)
    plain.run(frames, Trajectory(odometry))
    assert plain.report == {"fused": False, "rejected": len(plain.rejected)}


def test_degraded_odometry_never_beats_the_fused_warm_start():
    """The corridor ring with poor wheel odometry (5x the yaw noise, a yaw bias of 0.6 degrees per step, 10 %
    translation noise): the scans hold every direction they constrain and the odometry only the slide along
    the corridors, so the warm start stays far better than the odometry (here 29.6 m vs 0.37 m ATE)."""
    scans, truth, odometry = corridor_sequence(yaw_sigma=0.02, yaw_bias=0.01, trans_sigma=0.1)
    ws = IcpWarmStart(fuse="auto", progress=False)
    poses = ws.run(frames_from(scans, planar=True), Trajectory(odometry))
    assert ate(odometry, truth) > 10.0
    assert ate(poses, truth) < 0.05 * ate(odometry, truth) and ate(poses, truth) < 1.0
    assert ws.report["sources"]["scan across, odometry along"] > 0.3 * ws.report["steps"]


def test_the_truth_as_odometry_is_a_fixed_point(corridor):
    """Given the true poses as its odometry, the default warm start keeps them: the match cycles find that odometry
    the more precise source on every axis and weigh every match 0. Taken whole, the matches walk off (here 0.16 m)."""
    _, frames, truth, _ = corridor
    ws = IcpWarmStart(progress=False)
    poses = ws.run(frames, Trajectory(truth))
    assert ws.report["match_weights"]["weighed"] == "cycles" and max(ws.report["match_weights"]["weights"]) == 0.0
    np.testing.assert_allclose(poses, truth, atol=1e-9)
    whole = IcpWarmStart(weigh="whole", progress=False).run(frames, Trajectory(truth))
    assert ate(whole, truth) > 0.05
