"""Loop closure under large drift: correlative matching (global search, ambiguity), the cycle check,
and the ``loops`` topology on a drifted 2D floor."""

from __future__ import annotations

import numpy as np
import pytest
from plugins_scenes import floor_2d

from dm2_backend.algorithms import correlative as cm
from dm2_backend.algorithms.loop_graph import Closure, between, cycle_error
from dm2_backend.kernel.geometry import se3
from dm2_backend.plugins.registry import load
from dm2_backend.plugins.topology_loops import correct
from dm2_backend.simulate.path import drifting_odometry


def wall(a, b, spacing=0.05):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(np.linalg.norm(b - a) / spacing) + 1
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def room() -> np.ndarray:
    """An irregular room outline with a pillar: no symmetry, so one alignment is right."""
    walls = [((0, 0), (7, 0)), ((7, 0), (7, 3)), ((7, 3), (5, 5)), ((5, 5), (0, 5)), ((0, 5), (0, 0)),
             ((2, 2), (2.6, 2)), ((2.6, 2), (2.6, 2.4)), ((4.5, 1), (4.5, 1.8))]
    return np.concatenate([wall(a, b) for a, b in walls]) - np.array([3.0, 2.0])


def moved(xy: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """Points seen from a sensor at (x, y, yaw) in the target's frame: the inverse motion."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    return (xy - [x, y]) @ R


def test_correlative_finds_the_pose_far_from_the_guess():
    target = room()
    rng = np.random.default_rng(0)
    truth = (1.3, -0.8, np.radians(25.0))
    source = moved(target, *truth) + rng.normal(0, 0.01, target.shape)
    grid = cm.LikelihoodGrid(target, 0.1)
    got = cm.match(source, grid, (0.0, 0.0, 0.0), window_t=3.0, window_yaw=np.radians(40))
    assert abs(got.x - truth[0]) < 0.1 and abs(got.y - truth[1]) < 0.1
    assert abs(np.degrees(got.yaw - truth[2])) < 1.5
    assert got.score > 0.8 and got.runner_up < 0.9 * got.score
    # outside the window the pose cannot be found: the best in the window scores much lower
    narrow = cm.match(source, grid, (0.0, 0.0, 0.0), window_t=0.5, window_yaw=np.radians(5))
    assert narrow.score < 0.5 * got.score


def test_correlative_flags_a_corridor_as_ambiguous():
    corridor = np.concatenate([wall((-10, -1), (10, -1)), wall((-10, 1), (10, 1))])
    source = moved(corridor, 0.0, 0.0, 0.0)[np.abs(corridor[:, 0]) < 4]
    got = cm.match(source, cm.LikelihoodGrid(corridor, 0.1), (0.0, 0.0, 0.0), 3.0, np.radians(10))
    assert got.score > 0.9
    assert got.runner_up >= 0.9 * got.score  # sliding along the corridor scores the same
    assert got.runner_up_pose is not None and abs(got.runner_up_pose[0] - got.x) > 0.4


def test_cycle_error_is_zero_for_agreeing_closures_only():
    odo = np.array([[0, 0, 0], [1, 0, 0.1], [10, 5, 1.0], [11, 5.2, 1.1]], float)
    true = se3.to_xy_yaw(se3.from_xy_yaw(odo))
    # the loop: keyframes 2, 3 really lie here relative to 0, 1 (one rigid correction of both)
    true[2:] = se3.to_xy_yaw(se3.from_xy_yaw(np.array([[0.5, -0.3, 0.05]])) @ se3.from_xy_yaw(odo[2:]))
    c1 = Closure(0, 2, between(true[0], true[2]))
    c2 = Closure(1, 3, between(true[1], true[3]))
    et, er = cycle_error(odo, c1, c2)
    assert et < 1e-9 and er < 1e-9
    wrong = Closure(1, 3, c2.z + [1.0, 0.0, 0.0])
    assert cycle_error(odo, c1, wrong)[0] > 0.5


def test_correct_moves_keyframes_exactly_and_interpolates_between():
    poses = se3.from_xy_yaw(np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)]))
    odo = se3.to_xy_yaw(poses[[0, 4]])
    fixed = odo + [[0, 0, 0], [0, 1.0, 0]]
    out = correct(poses, np.array([0, 4]), odo, fixed)
    np.testing.assert_allclose(out[4, :2, 3], [4, 1], atol=1e-9)
    np.testing.assert_allclose(out[2, :2, 3], [2, 0.5], atol=1e-9)
    np.testing.assert_allclose(out[0], poses[0], atol=1e-12)


@pytest.fixture(scope="module")
def floor():
    return floor_2d()


def test_loops_closes_a_large_drift_loop(floor):
    frames, truth = floor
    # locally accurate (as scan matching is), globally drifting: about 20 degrees of yaw over the path
    drifted = drifting_odometry(truth, 1, 0.001, 0.01, 0.0015)
    topo = load("dm2.place_recognition", "loops")(progress=False).run(frames, drifted)
    assert topo.poses is not None and topo.poses.shape == truth.shape
    summary = topo.log[0]
    assert summary["closures"] >= 1 and topo.closures == summary["closures"] and topo.loop_closed
    # every accepted closure is a true revisit: its measured pose agrees with the truth
    accepted = [e for e in topo.log[1:] if e.get("accepted")]
    assert accepted
    for e in accepted:
        i, j = e["i"], e["j"]
        truth_z = se3.to_xy_yaw(se3.relative(truth[i][None], truth[j][None]))[0]
        assert np.hypot(*(truth_z[:2] - e["z"][:2])) < 0.15
    for e in topo.log[1:]:
        assert "reason" in e and "score" in e or "dropped" in e["reason"]

    def ate(P):
        return float(np.sqrt(np.mean(np.sum((P[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))

    assert ate(drifted) > 1.0
    assert ate(topo.poses) < 0.25 * ate(drifted)
    # the groups contain loop partners across the closed loop
    kinds = set(topo.edge_kind)
    assert "loop" in kinds


def test_a_closure_measured_again_on_short_submaps_is_not_turned_by_the_drift(floor):
    """A gyro bias turns each long submap (3 degrees over its length here); the closure measured on them takes
    a share of that turn. Measured again on submaps of the median range either side it is several times closer
    to the truth in yaw. From the truth nothing is bent: every closure keeps its long measurement, and the
    loop-closed poses are those without the second measurement."""
    frames, truth = floor
    drifted = drifting_odometry(truth, 1, 0.001, 0.01, 0.003)
    loops = load("dm2.place_recognition", "loops")

    def yaw_errors(topo):
        out = []
        for e in topo.log[1:]:
            if e.get("accepted"):
                true_yaw = se3.to_xy_yaw(se3.relative(truth[e["i"]][None], truth[e["j"]][None]))[0, 2]
                out.append(abs(np.degrees(se3.wrap_angle(true_yaw - e["z"][2]))))
        return np.array(out)

    short, long_only = loops(progress=False).run(frames, drifted), loops(progress=False, short_half_length=0).run(
        frames, drifted)
    assert short.log[0]["short_half_length"] == pytest.approx(frames.scale.range_median)
    measured = [e for e in short.log[1:] if e.get("accepted")]
    assert sum(e["short"]["kept"] for e in measured) >= 0.5 * len(measured)
    assert all("z_long" in e for e in measured if e["short"]["kept"])
    assert not any("short" in e for e in long_only.log[1:])
    assert np.median(yaw_errors(long_only)) > 1.0  # the long submaps' share of the bend
    assert np.median(yaw_errors(short)) < 0.3 * np.median(yaw_errors(long_only))
    from_truth = loops(progress=False).run(frames, truth)
    measured = [e for e in from_truth.log[1:] if e.get("accepted")]
    assert measured and all("short" in e and not e["short"]["kept"] and "z_long" not in e for e in measured)
    np.testing.assert_allclose(from_truth.poses, loops(progress=False, short_half_length=0).run(frames, truth).poses)


def test_loops_on_a_short_sequence_without_revisits(floor):
    """Fewer frames than a loop needs: no candidates, no loop-closed poses, groups still filled."""
    frames, truth = floor
    from dm2_backend.kernel.prepared import Frames

    few = Frames(frames.points[:5], None, True, frames.scale)
    topo = load("dm2.place_recognition", "loops")(progress=False, k=3).run(few, truth[:5])
    assert topo.poses is None  # nothing was loop-closed: the optimiser judges the warm start itself
    assert topo.closures == topo.log[0]["closures"] == 0 and (topo.groups >= 0).all()


def test_correlative_runner_up_sees_a_repeat_inside_the_best_block():
    """A pattern repeating every 6 cells: the shifted copy scores as well and must be reported, even when
    it falls in the same block of shifts as the best."""
    rng = np.random.default_rng(3)
    motif = rng.uniform(0, 0.5, (30, 2))
    pattern = np.concatenate([motif + [0.6 * k, 0] for k in range(-8, 9)])
    source = pattern[np.abs(pattern[:, 0]) < 2.0]
    got = cm.match(source, cm.LikelihoodGrid(pattern, 0.1), (0.3, 0.0, 0.0), 2.0, 0.0)
    assert got.runner_up >= 0.9 * got.score


def test_correct_keeps_keyframes_that_share_a_path_position():
    """Turning on the spot: two keyframes at the same path length keep their own corrections."""
    poses = se3.from_xy_yaw(np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1.0], [2, 0, 1.0]]))
    keys = np.array([0, 1, 2, 3])
    odo = se3.to_xy_yaw(poses)
    fixed = odo + [[0, 0, 0], [0, 0.1, 0], [0, 0.2, 0], [0, 0.3, 0]]
    out = correct(poses, keys, odo, fixed)
    np.testing.assert_allclose(se3.to_xy_yaw(out), fixed, atol=1e-9)


def test_loops_rejects_invalid_options(floor):
    from dm2_backend.runtime.errors import InputError

    frames, truth = floor
    with pytest.raises(InputError, match="resolution=-1"):
        load("dm2.place_recognition", "loops")(resolution=-1.0, progress=False).run(frames, truth)
    with pytest.raises(InputError, match="short_half_length=-1"):
        load("dm2.place_recognition", "loops")(short_half_length=-1.0, progress=False).run(frames, truth)
    with pytest.raises(InputError, match="short_gate=1.0"):
        load("dm2.place_recognition", "loops")(short_gate=1.0, progress=False).run(frames, truth)
    with pytest.raises(InputError, match="weak_score=0.6"):
        load("dm2.place_recognition", "loops")(weak_score=0.6, progress=False).run(frames, truth)
    with pytest.raises(InputError, match="drift_margin=-1"):
        load("dm2.place_recognition", "loops")(drift_margin=-1.0, progress=False).run(frames, truth)


def test_the_search_window_grows_at_the_drift_the_closures_measured(floor):
    """Every candidate is searched in the window the guessed rates give; one found ambiguous there is searched again
    in the window ``drift_margin`` times the accepted closures' measured rates give (their corrections over the path
    before each), never wider than the guess."""
    from dm2_backend.plugins.topology_loops import DriftRates

    frames, truth = floor
    drifted = drifting_odometry(truth, 1, 0.001, 0.01, 0.0015)
    lt = load("dm2.place_recognition", "loops")(progress=False)
    topo = lt.run(frames, drifted)
    L, entries = topo.log[0], [e for e in topo.log[1:] if "travelled" in e]
    for e in entries:
        first = e.get("wide", e)  # the first search: the guess
        # the keyframe's window: at least the guess over the candidate's path (a closure accepted at the same keyframe
        # resets the path that later candidates' corrections are measured over)
        guess = min(L["max_window"], L["window"] + lt.drift * e["travelled"])
        assert first["window"] >= guess - 0.01
        if "wide" in e:
            assert "ambiguous" in e["wide"]["reason"] and e["window"] < e["wide"]["window"]
    assert any("wide" in e for e in entries)  # this drifting floor has ambiguous candidates searched again
    learnt = DriftRates()
    learnt.add([Closure(0, 1, np.zeros(3), e) for e in entries if e.get("accepted")])
    rate_m, rate_deg = learnt.rates(lt.drift, lt.yaw_drift, lt.drift_margin)
    assert 0 < rate_m < lt.drift and 0 < rate_deg <= lt.yaw_drift  # it drifts less than the guess in translation
    assert DriftRates().rates(0.1, 0.5, 3.0) == (0.1, 0.5)  # no closure yet: the guess
    capped = DriftRates()
    capped.add([Closure(0, 1, np.zeros(3), {"offset": 5.0, "offset_deg": 50.0, "travelled": 10.0})])
    assert capped.rates(0.1, 0.5, 3.0) == (0.1, 0.5)  # never faster than the guess
    pooled = DriftRates()  # pooled over the path (3 x 1.5 m / 100 m), not the mean of each closure's rate
    pooled.add([Closure(0, 1, np.zeros(3), {"offset": 1.0, "offset_deg": 2.0, "travelled": 20.0}),
                Closure(0, 1, np.zeros(3), {"offset": 0.5, "offset_deg": 1.0, "travelled": 80.0})])
    assert pooled.rates(1.0, 10.0, 3.0) == pytest.approx((0.045, 0.09))
    across = DriftRates()  # a closure across a corridor holds the along-axis prediction: it measures yaw only
    across.add([Closure(0, 1, np.zeros(3), {"offset": 0.1, "offset_deg": 1.0, "travelled": 50.0},
                        axis=np.array([1.0, 0.0]))])
    assert across.rates(0.1, 0.5, 3.0) == pytest.approx((0.1, 0.06))


def test_a_match_scoring_a_little_under_the_gate_is_a_weak_closure(floor):
    """With the score gate above every true revisit's score, the revisits that pass every other test are weak
    closures (trusted when others agree around a cycle) and still true; without the weak tier none is taken."""
    frames, truth = floor
    drifted = drifting_odometry(truth, 1, 0.001, 0.01, 0.0015)
    loops = load("dm2.place_recognition", "loops")
    weak = loops(progress=False, min_score=0.99, weak_score=0.4).run(frames, drifted)
    accepted = [e for e in weak.log[1:] if e.get("accepted")]
    assert accepted and all(e["weak"] and "weak: score" in e["reason"] for e in accepted)
    for e in accepted:
        truth_z = se3.to_xy_yaw(se3.relative(truth[e["i"]][None], truth[e["j"]][None]))[0]
        assert np.hypot(*(truth_z[:2] - e["z"][:2])) < 0.15
    none = loops(progress=False, min_score=0.99, weak_score=0.99).run(frames, drifted)
    assert none.closures == 0 and all(not e.get("verified") for e in none.log[1:])
