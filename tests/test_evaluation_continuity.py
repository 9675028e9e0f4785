"""A step that neither the odometry nor the registration of its two frames explains is a cut; nothing else is."""

from __future__ import annotations

import numpy as np
import pytest

from dm2_backend.evaluation.continuity import MIN_STEPS, Cuts, cuts
from dm2_backend.kernel.geometry import se3

SLIP, RANGE = 0.3, 2.5  # how far a scan-matching step slides (m) and the scans' median range (m)


def _walk(n: int, seed: int = 0) -> np.ndarray:
    """A hand-held path: 5 cm steps with small turns, about every axis."""
    rng = np.random.default_rng(seed)
    steps = se3.make_poses(se3.exp_so3(rng.normal(0, 0.02, (n - 1, 3))),
                           np.column_stack([np.full(n - 1, 0.05), rng.normal(0, 0.01, (n - 1, 2))]))
    return _chain(steps)


def _chain(steps: np.ndarray) -> np.ndarray:
    poses = [np.eye(4)]
    for T in steps:
        poses.append(poses[-1] @ T)
    return np.stack(poses)


def _measured(truth: np.ndarray, sigma_t: float, sigma_r: float, seed: int) -> np.ndarray:
    """The true steps with independent noise: (N-1, 4, 4)."""
    rng = np.random.default_rng(seed)
    noise = se3.make_poses(se3.exp_so3(rng.normal(0, sigma_r, (len(truth) - 1, 3))),
                           rng.normal(0, sigma_t, (len(truth) - 1, 3)))
    return se3.relative(truth[:-1], truth[1:]) @ noise


def _registered(truth: np.ndarray, seed: int = 1) -> dict[int, np.ndarray]:
    return dict(enumerate(_measured(truth, 0.003, 0.002, seed)))


def _cut_at(poses: np.ndarray, step: int, offset: np.ndarray) -> np.ndarray:
    """Every pose after ``step`` moved by ``offset`` (expressed in the frame of pose ``step``)."""
    out = poses.copy()
    out[step + 1:] = poses[step] @ offset @ se3.inverse(poses[step]) @ poses[step + 1:]
    return out


@pytest.fixture(scope="module")
def truth() -> np.ndarray:
    return _walk(600)


@pytest.fixture(scope="module")
def odometry(truth) -> np.ndarray:
    """The front end's poses: the true steps with 2 mm / 0.1 deg noise each, chained (they drift)."""
    return _chain(_measured(truth, 0.002, 0.002, seed=2))


def test_the_truth_and_the_odometry_are_not_cut(truth, odometry):
    for poses in (truth, odometry):
        found = cuts(poses, odometry, _registered(truth), SLIP, RANGE)
        assert found.judged and not found and found.describe() == ""
    # a loop correction spread along the path (1 m over 600 steps) moves every step a little: no cut
    spread = odometry.copy()
    spread[:, :3, 3] += np.linspace(0, 1.0, len(odometry))[:, None] * np.array([0.6, 0.8, 0.0])
    assert not cuts(spread, odometry, _registered(truth), SLIP, RANGE)


def test_a_cut_step_is_found_where_it_is(truth, odometry):
    offset = se3.make_poses(se3.exp_so3(np.array([0.0, 0.0, 0.6])), np.array([0.9, -0.4, 0.1]))
    broken = _cut_at(odometry, 235, offset)
    found = cuts(broken, odometry, _registered(truth), SLIP, RANGE)
    assert found.steps.tolist() == [235]
    assert found.offset_m[0] == pytest.approx(np.linalg.norm([0.9, -0.4, 0.1]), rel=0.05)
    assert found.offset_deg[0] == pytest.approx(np.degrees(0.6), rel=0.05)
    assert found.describe().startswith("step 235 (")
    assert found.summary()["steps"] == [235]
    # without any registration the odometry alone judges, and finds the same step
    assert cuts(broken, odometry, {}, SLIP, RANGE).steps.tolist() == [235]
    # a step that front end and registration both got wrong by less than a slip (a scan-matching step that slid
    # where the scans leave a direction free): the solution that repairs it is not called a cut
    slid = _cut_at(odometry, 235, se3.make_poses(np.eye(3), np.array([0.8 * SLIP, 0.0, 0.0])))
    registered = _registered(truth)
    registered[235] = se3.relative(slid[235], slid[236])
    assert not cuts(odometry, slid, registered, SLIP, RANGE)
    assert cuts(odometry, slid, registered, 0.5 * SLIP, RANGE).steps.tolist() == [235]


def test_a_front_end_jump_that_the_registration_measures_is_not_a_cut(truth, odometry):
    jump = se3.make_poses(se3.exp_so3(np.array([0.0, 0.3, 0.0])), np.array([0.5, 0.0, 0.0]))
    jumped = _cut_at(odometry, 300, jump)  # the front end jumped at step 300; the scans did not
    # the truth (and a solution that repairs the jump) leaves the odometry there, as the registration says
    assert not cuts(truth, jumped, _registered(truth), SLIP, RANGE)
    # the registration of that step failed: the odometry alone calls the repair a cut
    registered = _registered(truth)
    del registered[300]
    assert cuts(truth, jumped, registered, SLIP, RANGE).steps.tolist() == [300]


def test_too_short_a_sequence_is_not_judged(truth, odometry):
    jump = se3.make_poses(np.eye(3), np.array([1.0, 0.0, 0.0]))
    short = _cut_at(odometry[: MIN_STEPS], 5, jump)  # MIN_STEPS - 1 steps
    found = cuts(short, odometry[: MIN_STEPS], {}, SLIP, RANGE)
    assert not found and not found.judged
    just = _cut_at(odometry[: MIN_STEPS + 1], 5, jump)  # MIN_STEPS steps: judged
    assert cuts(just, odometry[: MIN_STEPS + 1], {}, SLIP, RANGE).steps.tolist() == [5]


def test_the_description_names_the_largest_cuts_in_translation_or_rotation():
    found = Cuts(np.array([10, 20, 30]), np.array([1.0, 0.05, 0.5]), np.array([2.0, 60.0, 1.0]))
    assert found.describe(most=2) == ("step 10 (1 m, 2 deg from the odometry), step 20 (0.05 m, 60 deg from the "
                                      "odometry) and 1 more")
