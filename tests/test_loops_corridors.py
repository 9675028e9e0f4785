"""Loop closure in corridors: a match that is ambiguous only along one line becomes a closure across it
(certain across and in yaw, free along), trusted on more agreement than a plain one; the graph settles the
position along. Weak closures (overlap a little under the gate) need the same extra agreement."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import frames_from

from dm2_backend.algorithms import correlative as cm
from dm2_backend.algorithms.loop_graph import Closure, KeyframeGraph, closure_error, confirms, cycle_error
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.topology_loops import LoopsTopology
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.simulate.corridor import corridor_sequence


def _corridor(length: float = 12.0, spacing: float = 0.03) -> np.ndarray:
    x = np.arange(-length / 2, length / 2, spacing)
    return np.concatenate([np.column_stack([x, np.full_like(x, -1.0)]), np.column_stack([x, np.full_like(x, 1.0)])])


def test_ridge_along_a_corridor_gives_its_axis():
    walls = _corridor()
    scan = walls[np.abs(walls[:, 0]) < 3][::3]
    m = cm.match(scan, cm.LikelihoodGrid(walls, 0.05), (0.3, 0.1, 0.02), 1.0, np.radians(5))
    assert m.runner_up >= 0.9 * m.score  # ambiguous ...
    assert m.axis is not None and abs(m.axis[0]) > 0.99  # ... along x only
    assert abs(m.y) < 0.03 and abs(m.yaw) < np.radians(1.5)  # and certain across and in yaw


def test_no_axis_when_the_match_is_certain_or_ambiguous_in_two_directions():
    walls = _corridor()
    end = np.column_stack([np.full(60, 4.0), np.linspace(-1, 1, 60)])  # an end wall pins the corridor
    closed = np.concatenate([walls, end])
    scan = np.concatenate([walls[np.abs(walls[:, 0]) < 3][::3], end[::3]])
    m = cm.match(scan, cm.LikelihoodGrid(closed, 0.05), (0.3, 0.1, 0.02), 1.0, np.radians(5))
    assert m.axis is None and m.runner_up < 0.9 * m.score
    # a grid of posts: equally good alignments in x and y, not on one line
    g = np.arange(-6, 6.01, 1.0)
    posts = np.array([(x, y) for x in g for y in g]) + np.random.default_rng(0).normal(0, 0.005, (len(g) ** 2, 2))
    m = cm.match(posts[np.linalg.norm(posts, axis=1) < 3], cm.LikelihoodGrid(posts, 0.05), (0.2, 0.2, 0.0), 1.5,
                 np.radians(3))
    assert m.runner_up >= 0.9 * m.score and m.axis is None


def test_cycle_check_and_residual_leave_a_corridor_closures_axis_out():
    odo = np.array([[0.0, 0, 0], [5.0, 0, 0], [20.0, 0, np.pi], [25.0, 0, np.pi]])
    # the truth: keyframe 2 lies 0.3 m behind where the odometry puts it (along x)
    along = np.array([1.0, 0.0])
    c1 = Closure(0, 2, np.array([20.0 + 0.3, 0.0, np.pi]), axis=along)  # measured along = wrong by 0.3 m
    c2 = Closure(1, 3, np.array([20.0, 0.0, np.pi]), axis=along)
    et, er = cycle_error(odo, c1, c2)
    assert et < 1e-9 and er < 1e-9  # the along error does not count
    c1.z[1] += 0.2  # 0.2 m across: counts
    assert cycle_error(odo, c1, c2)[0] == pytest.approx(0.2)
    plain = Closure(0, 2, c1.z.copy())
    assert cycle_error(odo, plain, Closure(1, 3, np.array([20.0, 0.0, np.pi])))[0] == pytest.approx(np.hypot(0.3, 0.2))
    crossing = Closure(1, 3, np.array([20.0, 0.0, np.pi]), axis=np.array([0.0, 1.0]))
    assert cycle_error(odo, c1, crossing)[0] == np.inf  # two crossing axes cannot check each other
    tilted = Closure(1, 3, np.array([20.0, 0.0, np.pi]), axis=np.array([np.cos(0.17), np.sin(0.17)]))  # 10 deg
    et = cycle_error(odo, c1, tilted)[0]  # nearly parallel: one axis dropped, the rest still checked
    assert 0.15 < et < 0.25
    sigma = np.array([0.1, 0.1, 0.01])
    poses = odo.copy()
    assert closure_error(poses, c1, sigma) == pytest.approx(0.2 / 0.1)
    assert closure_error(poses, plain, sigma) == pytest.approx(np.hypot(0.3, 0.2) / 0.1)


def test_weak_and_corridor_closures_need_more_agreement():
    full, weak, across = Closure(0, 1, np.zeros(3)), Closure(0, 1, np.zeros(3), weak=True), Closure(
        0, 1, np.zeros(3), weak=True, axis=np.array([1.0, 0.0]))
    assert confirms(full, [full]) and confirms(full, [weak])
    assert not confirms(weak, [weak]) and confirms(weak, [weak, across]) and confirms(weak, [full])
    assert not confirms(full, [])


def test_graph_settles_a_corridor_closure_along_its_axis():
    """Keyframes on a straight corridor, odometry 1 m short over the loop: a closure across the corridor fixes
    the lateral offset and leaves the along-corridor position to the odometry."""
    odo = np.array([[x, 0.0, 0.0] for x in range(11)])
    odo_sigma = np.tile([0.05, 0.05, 0.002], (10, 1))
    g = KeyframeGraph(odo, odo_sigma, np.array([0.05, 0.05, 0.005]))
    g.extend(10)
    # keyframe 10 is really at (10, 0.1) seen from 0; the match says 7 m along (not measured) and 0.1 m across
    g.close([Closure(0, 10, np.array([7.0, 0.1, 0.0]), axis=np.array([1.0, 0.0]))])
    assert 0.08 < g.estimate[10, 1] < 0.105  # most of the way: the odometry chain is 10 steps of 5 cm sigma
    assert g.estimate[10, 0] == pytest.approx(10.0, abs=0.05)  # the bogus along value (7 m) is ignored


def test_corridor_closure_information_turns_with_the_measured_heading():
    """Keyframe b turned 45 degrees from a: the free axis (a's x) must stay free in the factor's residual frame
    (b's measured frame), or the bogus along value would pull b back along x."""
    odo = np.array([[x, 0.0, 0.0] for x in range(10)] + [[10.0, 0.0, np.pi / 4]])
    g = KeyframeGraph(odo, np.tile([0.05, 0.05, 0.002], (10, 1)), np.array([0.05, 0.05, 0.005]))
    g.extend(10)
    g.close([Closure(0, 10, np.array([7.0, 0.1, np.pi / 4]), axis=np.array([1.0, 0.0]))])
    assert g.estimate[10, 0] == pytest.approx(10.0, abs=0.05)
    assert 0.08 < g.estimate[10, 1] < 0.105


@pytest.fixture(scope="module")
def ring():
    scans, truth, odometry = corridor_sequence()
    frames = frames_from(scans, planar=True)
    warm = IcpWarmStart(progress=False).run(frames, Trajectory(odometry))
    return frames, truth, warm


def _ate(p: np.ndarray, t: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p[:, :2, 3] - t[:, :2, 3]) ** 2, axis=1))))


def test_corridor_ring_closes_across_corridors(ring):
    frames, truth, warm = ring
    topo = LoopsTopology(progress=False).run(frames, warm)
    accepted = [e for e in topo.log[1:] if e.get("accepted")]
    across = [e for e in accepted if "axis" in e]
    assert len(across) >= 10 and len(accepted) > len(across)
    for e in across:
        rel = np.linalg.inv(truth[e["i"]]) @ truth[e["j"]]
        d = np.array(e["z"][:2]) - rel[:2, 3]
        u = np.array(e["axis"])
        assert np.linalg.norm(d - (d @ u) * u) < 0.03  # certain across
        assert abs(np.degrees(se3.wrap_angle(e["z"][2] - np.arctan2(rel[1, 0], rel[0, 0])))) < 0.5
        assert "across a corridor" in e["reason"]
    assert _ate(topo.poses, truth) < 0.8 * _ate(warm, truth)
    off = LoopsTopology(progress=False, across_corridors=False).run(frames, warm)
    assert not any("axis" in e for e in off.log[1:])
    assert sum(bool(e.get("accepted")) for e in off.log[1:]) < len(accepted)


@pytest.mark.parametrize("option", [{"max_ambiguity": 1.2}, {"weak_fitness": 0.6}, {"weak_fitness": -0.1}])
def test_loops_refuses_bad_ambiguity_and_weak_settings(ring, option):
    from dm2_backend.runtime.errors import InputError

    frames, _, warm = ring
    with pytest.raises(InputError, match=next(iter(option))):
        LoopsTopology(progress=False, **option).run(frames, warm)
