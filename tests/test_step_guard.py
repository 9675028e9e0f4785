"""The step guard: every step of a result is judged by its two frames' own data (the residual at the step against
the residual at the pair's registration or the odometry step); contradicted steps are held and solved again, so a
step the data contradicts is never returned. Also what it stands on: exact (unrobust) graph edges, a registration
for every step, and the repair of a front-end step the frames clearly contradict in a view of few surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from dm2_backend.algorithms.common import Cloud, assemble
from dm2_backend.algorithms.gates import plane_residuals, significantly_worse
from dm2_backend.evaluation.step_check import ODOMETRY, REGISTRATION, FramePairs, StepJudge
from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.solver_options import SolverOptions
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline import step_guard

ROOM = np.array([[-4.0, -2.5, -1.2], [4.0, 2.5, 1.8]])  # box corners (m)


def scan_of_room(pose: np.ndarray, n: int = 3000, seed: int = 0, noise: float = 0.005) -> np.ndarray:
    """A depth camera's returns (90 x 70 degrees, looking along its x axis) of the room's walls, floor and ceiling
    from ``pose``, in the camera frame."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(-0.8, 0.8, n), rng.uniform(-0.6, 0.6, n)
    d = pose[:3, :3] @ np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    at = pose[:3, 3][:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (ROOM[1][:, None] - at) / d, np.where(d < 0, (ROOM[0][:, None] - at) / d, np.inf))
    r = t.min(0)
    r = r + rng.normal(0.0, noise, r.shape)
    return (pose[:3, :3].T @ (d * r)).T


@pytest.fixture(scope="module")
def room_sequence() -> tuple[list[np.ndarray], np.ndarray]:
    """30 frames 5 cm apart across the room (turning slowly towards a corner), and their true poses."""
    xy = np.column_stack([np.linspace(-2.0, -0.55, 30), np.linspace(0.0, 0.3, 30)])
    truth = se3.from_xy_yaw(np.column_stack([xy, np.linspace(0.0, 0.3, 30)]))
    return [scan_of_room(T, seed=i) for i, T in enumerate(truth)], truth


def steps_of(poses: np.ndarray) -> dict[int, np.ndarray]:
    return dict(enumerate(se3.relative(poses[:-1], poses[1:])))


def judge_of(scans: list[np.ndarray], truth: np.ndarray, seed: int = 0) -> StepJudge:
    """References as a preparation gives them: registrations a few mm off the true steps, the odometry exact."""
    rng = np.random.default_rng(seed)
    noisy = {i: T @ se3.from_xyz_euler(np.r_[rng.normal(0, 0.002, 3), rng.normal(0, 0.0005, 3)])
             for i, T in steps_of(truth).items()}
    return StepJudge(FramePairs(scans, False, 0.15, 0.001), {REGISTRATION: noisy, ODOMETRY: steps_of(truth)})


def broken_at(poses: np.ndarray, step: int, offset: np.ndarray) -> np.ndarray:
    """``poses`` with step ``step`` moved by ``offset`` (x y z roll pitch yaw) and the rest moving with it."""
    out = poses.copy()
    out[step + 1:] = poses[step] @ se3.from_xyz_euler(offset) @ se3.relative(poses[step], poses[step + 1:])
    return out


def rechained(poses: np.ndarray, held: dict[int, step_guard.Hold]) -> np.ndarray:
    """The least a solver does with held steps: each held step takes its held pose, the others keep theirs."""
    steps = steps_of(poses) | {i: h.relative for i, h in held.items()}
    out = [poses[0]]
    for i in range(len(poses) - 1):
        out.append(out[-1] @ steps[i])
    return np.array(out)


def test_a_step_moved_off_its_data_is_contradicted_and_the_truth_is_not(room_sequence):
    scans, truth = room_sequence
    judge = judge_of(scans, truth)
    clean = judge.check(truth)
    assert len(clean.steps) == len(truth) - 1 and clean.count == 0
    broken = judge.check(broken_at(truth, 12, np.r_[0.08, -0.05, 0.0, 0.0, 0.0, 0.0]))
    assert broken.steps[broken.contradicted].tolist() == [12]
    k = int(np.flatnonzero(broken.steps == 12)[0])
    assert broken.residual_m[k] > 1.5 * broken.reference_residual_m[k]
    # the step is compared with the reference its data fits best: the exact odometry here
    assert broken.reference[k] == ODOMETRY and np.allclose(broken.reference_step[k], steps_of(truth)[12])
    record = broken.summary()
    assert record["contradicted"] == [12] and len(record["excess"]) == len(truth) - 1
    assert "step 12" in broken.describe()


def test_a_step_whose_frames_match_nothing_is_not_judged_and_the_record_names_steps(room_sequence):
    """An empty frame leaves its two steps unjudged; the verdicts and the record still name steps, not rows; a
    step that slides the frames apart is judged on the points it lost."""
    scans, truth = room_sequence
    scans = list(scans)
    scans[2] = np.zeros((0, 3))
    judge = judge_of(scans, truth)
    slid = broken_at(truth, 12, np.r_[2.0, 0.0, 0.0, 0.0, 0.0, 2.5])  # no point of frame 13 near frame 12's
    check = judge.check(slid)
    assert 1 not in check.steps.tolist() and 2 not in check.steps.tolist()
    assert check.steps[check.contradicted].tolist() == check.summary()["contradicted"] == [12]
    assert judge.fit(slid) > judge.fit(truth) and np.isinf(judge.fit(np.full_like(truth, np.nan)))


def test_a_small_offset_within_the_noise_is_not_contradicted(room_sequence):
    """A few millimetres, what a multi-frame solution and the pairwise registrations differ by, stands."""
    scans, truth = room_sequence
    judge = judge_of(scans, truth)
    assert judge.check(broken_at(truth, 12, np.r_[0.002, 0.001, 0.0, 0.0, 0.0, 0.0005])).count == 0


def test_the_guard_holds_what_is_contradicted_and_leaves_the_truth_alone(room_sequence):
    scans, truth = room_sequence
    judge = judge_of(scans, truth)
    calls = []

    def resolve(poses, held):
        calls.append(sorted(held))
        return rechained(poses, held)

    untouched = step_guard.guard(judge, truth, resolve)
    assert untouched.clean and not untouched.held and not calls and untouched.poses is truth
    guarded = step_guard.guard(judge, broken_at(truth, 12, np.r_[0.0, 0.1, 0.0, 0.0, 0.0, 0.02]), resolve)
    assert guarded.clean and sorted(guarded.held) == [12] and calls == [[12]]
    step = se3.relative(guarded.poses[12], guarded.poses[13])
    assert np.linalg.norm(se3.relative(steps_of(truth)[12], step)[:3, 3]) < 0.01
    assert guarded.summary()["held"] == [12] and guarded.summary()["rounds"][0]["contradicted"] == [12]


def test_a_tension_handed_to_the_next_step_is_held_by_a_wider_stretch(room_sequence):
    """A solver that moves the break to the neighbouring step when a step is held: each round holds a stretch
    twice as wide around what is contradicted, until none is."""
    scans, truth = room_sequence
    judge = judge_of(scans, truth)
    offset = np.r_[0.0, 0.1, 0.0, 0.0, 0.0, 0.0]

    def resolve(poses, held):
        free = [i for i in range(10, 20) if i not in held]
        return broken_at(rechained(truth, held), free[0], offset) if free else rechained(truth, held)

    guarded = step_guard.guard(judge, broken_at(truth, 10, offset), resolve)
    assert guarded.clean
    assert [r.contradicted for r in guarded.rounds] == [(10,), (11,), (13,), (17,)]
    assert sorted(guarded.held) == list(range(10, 25))


def test_the_guard_gives_up_after_its_rounds(room_sequence):
    scans, truth = room_sequence
    judge = judge_of(scans, truth)
    always = broken_at(truth, 5, np.r_[0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    guarded = step_guard.guard(judge, always, lambda poses, held: always)
    assert not guarded.clean and len(guarded.rounds) == step_guard.ROUNDS and guarded.check.count == 1


def chain_graph(wrong_step: float) -> PoseGraph:
    """Five poses 1 m apart; the odometry edge 2->3 says ``wrong_step`` m instead, and a strong loop edge 0->4
    agrees with the others."""
    truth = se3.from_xyz_euler(np.column_stack([np.arange(5.0), np.zeros((5, 5))]))
    graph = PoseGraph.from_trajectory(Trajectory(poses=truth))
    graph.relative[2] = se3.from_xyz_euler(np.r_[wrong_step, 0, 0, 0, 0, 0])
    graph.information[:] = np.eye(6) * 1e4
    return PoseGraph(graph.ids, truth, np.vstack([graph.edges, [0, 4]]),
                     np.concatenate([graph.relative, se3.relative(truth[:1], truth[4:])]),
                     np.concatenate([graph.information, [np.eye(6) * 1e6]]))


def test_a_held_step_is_an_exact_edge_the_robust_kernel_does_not_give_up():
    cauchy = SolverOptions(robust="cauchy")
    graph = chain_graph(3.0)
    free = gtsam_solver.optimize(graph, cauchy).poses
    assert abs(se3.relative(free[2], free[3])[0, 3] - 1.0) < 0.01  # the kernel gave up the wrong odometry edge
    held = graph.holding(np.array([2]), se3.from_xyz_euler(np.r_[1.5, 0, 0, 0, 0, 0])[None], np.eye(6)[None] * 1e6)
    assert held.exact.tolist() == [False] * 5 + [True] and len(held.edges) == 6
    solved = gtsam_solver.optimize(held, cauchy).poses
    assert se3.relative(solved[2], solved[3])[0, 3] == pytest.approx(1.5, abs=1e-3)
    # the same edge under the kernel is given up as the wrong odometry edge was
    from dataclasses import replace

    robust = gtsam_solver.optimize(replace(held, exact=None), cauchy).poses
    assert abs(se3.relative(robust[2], robust[3])[0, 3] - 1.0) < 0.05
    none = held.holding(np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)))
    assert none.exact.tolist() == held.exact.tolist()


def test_every_step_is_in_its_anchors_group():
    """However many better candidates fill a group, frame i+1 is in frame i's: each step is registered."""
    n, k = 12, 3
    far = [[((i + 5) % n, "loop"), ((i + 6) % n, "radius"), ((i + 7) % n, "radius"), ((i + 8) % n, "radius")]
           for i in range(n)]
    topo = assemble(far, k)
    for i in range(n - 1):
        assert i + 1 in topo.groups[i].tolist()
        assert (i + 5) % n in topo.groups[i].tolist()  # the loop candidate stays
    assert (topo.groups >= 0).all()


def wall_view(seed: int, bump: bool, width: float = 1.5) -> np.ndarray:
    """A depth camera 2 m from a wall (z forward) seeing ``width`` m either side, with a small box on it or not."""
    rng = np.random.default_rng(seed)
    n = int(800 * width)
    wall = np.column_stack([rng.uniform(-width, width, n), rng.uniform(-1.0, 1.0, n), np.full(n, 2.0)])
    if bump:
        side = rng.uniform(-0.15, 0.15, (120, 2))
        box = np.column_stack([np.full(120, 0.3), side[:, 0], 1.85 + side[:, 1] + 0.15])  # a face across the wall
        wall = np.vstack([wall, box])
    return wall + rng.normal(0.0, 0.003, wall.shape)


def test_a_degenerate_view_repairs_a_step_its_frames_contradict_but_not_one_along_the_free_direction():
    """One wall and a small box: the translation constraint fails, yet a front-end step 0.3 m off the wall's
    normal is contradicted by the frames and repaired; a step 0.3 m along a wall that the second frame sees only a
    part of leaves every point on it: the frames cannot tell, and the front end's step is kept."""
    from plugins_scenes import frames_from

    from dm2_backend.algorithms.icp import register
    from dm2_backend.plugins.topology_loops3d import Loops3dTopology

    true = se3.from_xyz_euler(np.r_[0.01, 0.0, 0.005, 0, 0, 0])
    cases = ((wall_view(0, True), wall_view(1, True), np.r_[0.0, 0.0, 0.3], True),
             (wall_view(0, False, 2.5), wall_view(1, False, 1.5), np.r_[0.3, 0.0, 0.0], False))
    for a, b_view, front_end, replaced in cases:
        b = se3.transform_points(se3.inverse(true), b_view)
        frames = frames_from([a, b], planar=False, max_points=4096)
        topology = Loops3dTopology(progress=False)
        topology._setup(frames)
        fine = topology._lengths["fine"]
        src, tgt = Cloud(frames.points[1], False, 2 * fine), Cloud(frames.points[0], False, 2 * fine)
        step = true @ se3.from_xyz_euler(np.r_[front_end, 0, 0, 0])
        match = register(src, tgt, true, (4 * fine, fine), "gicp")
        gates = {f.gate.name for f in topology._gates(src, tgt, match, {})}
        assert gates == {"DEGENERATE"}  # one wall: the closure gates alone would refuse the registration
        assert topology._replaces(src, tgt, match, step) is replaced
        assert significantly_worse(src, tgt, step, match.T, fine) is replaced
        assert np.isfinite(plane_residuals(src, tgt, match.T, fine)).mean() > 0.9


def test_the_console_names_held_stretches_and_the_profile_gets_the_guards_marks():
    from dm2_backend.pipeline.dense_start import spans
    from dm2_backend.pipeline.run_writer import guard_marks

    assert spans([3, 4, 5, 9, 11, 12]) == "3-5, 9, 11-12" and spans([]) == ""
    details = {"start": {"dense": {"step_guard": {"held": [4, 5], "check": {"contradicted": [7]}}}}}
    assert guard_marks(details) == {"held": [4, 5], "contradicted": [7]}
    assert guard_marks({"start": {"dense": {}}}) == {} and guard_marks({}) == {}


def test_no_first_order_epochs_after_a_dense_stage_whose_result_was_not_kept(room_sequence, monkeypatch):
    """The dense result agrees worse with the others' planes, so the start stands; the first-order epochs do not
    then trade its steps for a sharper map: they run only where the dense stage did not. The report gives how well
    the start's and the result's steps fit their frames."""
    from optim_cases import frames_of

    from dm2_backend.config.optimiser import OptimConfig
    from dm2_backend.config.schema import RunConfig
    from dm2_backend.kernel.prepared import Pairwise, Topology
    from dm2_backend.kernel.scans import Scan, ScanSequence
    from dm2_backend.optim.dense import DenseResult
    from dm2_backend.pipeline import dense_start as start_module
    from dm2_backend.pipeline.parallel import build
    from dm2_backend.prepare.steps import Prepared

    scans, truth = room_sequence
    n = len(scans)
    empty = Pairwise(np.zeros((n, 0, 4, 4)), np.zeros((n, 0), bool), np.zeros((n, 0)), np.zeros((n, 0)))
    prep = Prepared(frames_of(scans, planar=False, max_points=3000), truth, Topology(np.zeros((n, 0), int)), empty)
    seq = ScanSequence(lambda i: Scan(scans[i]), n, planar=False)
    wobble = np.random.default_rng(3).normal(0, 0.01, (n, 3))
    wobbly = truth @ se3.from_xyz_euler(np.column_stack([wobble, np.zeros((n, 3))]))
    monkeypatch.setattr(start_module, "refine_dense", lambda *a, **k: DenseResult(wobbly, [], 0.0))
    monkeypatch.setattr(start_module, "agreement_score",
                        lambda *a, **k: {"warm start": 1.0, "prepared": 0.5, "dense": 0.9})
    given = start_module.Start(truth, start_module.StartKind.PREPARED, "the prepared poses")
    out = start_module.dense_start(seq, prep, given, OptimConfig())
    np.testing.assert_array_equal(out.poses, truth)
    assert out.dense.returned is start_module.Kept.PREPARED and out.dense_ran and not out.refined
    assert out.dense.step_guard.check.fit_m > out.dense.start_fit_m  # the wobbly steps fit worse
    assert build(prep, out, RunConfig(), progress=False).epochs == 0
    assert build(prep, start_module.Start(truth, start_module.StartKind.PREPARED, "no dense stage"), RunConfig(),
                 progress=False).epochs > 0
