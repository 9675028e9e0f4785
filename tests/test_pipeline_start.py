"""Where refine's optimiser starts: the pose-graph solution when its frames agree better with the planes the others
make (or, without the dense stage, its map is sharper), else the prepared poses."""

from __future__ import annotations

import numpy as np
import pytest
from optim_cases import one_thread, perturb, planar_case
from pydantic import ValidationError

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.evaluation.map_quality import MapSampler
from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.graph_edges import build_graph
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.kernel.solver_options import GraphResult
from dm2_backend.optim.stop import StopReason
from dm2_backend.pipeline import start as start_module
from dm2_backend.pipeline.live import ate_rmse
from dm2_backend.pipeline.start import GRAPH_SOLVER, Kept, StartKind, StartReason, choose_start
from dm2_backend.prepare.steps import Prepared


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def prepared() -> Prepared:
    case = planar_case()
    return Prepared(case.frames, case.warm, case.topology, case.pairwise)


@pytest.fixture(scope="module")
def sampler() -> MapSampler:
    scans = planar_case().scans
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), planar=True)
    return MapSampler.from_scans(seq)


def test_graph_start_is_the_gtsam_baseline_when_sharper(prepared, sampler):
    start = choose_start(prepared, OptimConfig(start="graph"), sampler)
    graph = build_graph(prepared.frames, prepared.initial, prepared.topology, prepared.pairwise)
    np.testing.assert_allclose(start.poses, gtsam_solver.optimize(graph, GRAPH_SOLVER).poses)
    assert start.name is StartKind.GRAPH and start.map_entropy["graph"] < start.map_entropy["prepared"]
    assert sampler.entropy(start.poses) == pytest.approx(start.map_entropy["graph"])


def test_a_blurrier_graph_solution_is_not_taken(prepared, sampler, monkeypatch):
    def bent(graph, options):
        return GraphResult(perturb(graph.poses, 0.5, 0.05, seed=3), None, None, None, 0.0, "gtsam")

    monkeypatch.setattr(start_module.gtsam_solver, "optimize", bent)
    start = choose_start(prepared, OptimConfig(start="graph"), sampler)
    assert start.name is StartKind.PREPARED and start.reason is StartReason.MAP_SHARPNESS
    assert start.map_entropy["graph"] > start.map_entropy["prepared"]
    np.testing.assert_array_equal(start.poses, prepared.initial)


def test_a_graph_solution_that_cuts_the_sequence_is_not_taken(prepared, sampler, monkeypatch):
    """A clique of wrong registrations that cut one odometry edge (both stretches kept whole, so their maps stay
    sharp): the steps show it, and the prepared poses start."""
    def cut(graph, options):
        poses = graph.poses.copy()
        poses[31:] = se3.from_xy_yaw(np.array([1.0, 0.5, 0.4])) @ poses[31:]
        return GraphResult(poses, None, None, None, 0.0, "gtsam")

    monkeypatch.setattr(start_module.gtsam_solver, "optimize", cut)
    start = choose_start(prepared, OptimConfig(start="graph"), sampler)
    assert start.name is StartKind.PREPARED and start.reason is StartReason.GRAPH_CUTS
    assert start.graph_cuts.steps.tolist() == [30] and start.summary()["cuts"] == {"graph": start.graph_cuts.summary()}
    np.testing.assert_array_equal(start.poses, prepared.initial)
    # the unbroken graph solution is judged and kept
    monkeypatch.undo()
    kept = choose_start(prepared, OptimConfig(start="graph"), sampler)
    assert kept.name is StartKind.GRAPH and kept.graph_cuts.judged and not kept.graph_cuts


def test_the_dense_stages_cells_judge_the_graph_start(prepared, monkeypatch):
    """With the dense stage's cells the graph start is judged by how far each frame lies from the planes the other
    frames make (map entropy chose a depth camera's graph solution 7x farther from the truth than the loop-closed
    poses): the judge ranks the truth first, keeps the graph when its frames agree better and refuses a bent one."""
    from dm2_backend.pipeline.dense_start import DenseCells

    case = planar_case()
    seq = ScanSequence(lambda i: Scan(case.scans[i]), len(case.scans), planar=True)
    judge = DenseCells.of(seq, prepared, OptimConfig())
    bent_poses = perturb(case.gt, 0.1, 0.02, seed=3)
    ranked = judge.agreement({"truth": case.gt, "bent": bent_poses})
    assert ranked["truth"] < 0.5 * ranked["bent"]
    start = choose_start(prepared, OptimConfig(start="graph"), None, judge)
    solved = gtsam_solver.optimize(build_graph(prepared.frames, prepared.initial, prepared.topology,
                                                prepared.pairwise), GRAPH_SOLVER).poses
    again = judge.agreement({"prepared": prepared.initial, "graph": solved})
    assert start.agreement_m2 == pytest.approx(again) and start.summary()["agreement_m2"] == start.agreement_m2
    better = "graph" if again["graph"] <= again["prepared"] else "prepared"
    assert start.name.value == better and not start.map_entropy
    # each candidate's own error agrees with the judge here: the one it keeps is the closer to the truth
    assert ate_rmse(case.gt, start.poses) <= ate_rmse(case.gt, solved if better == "prepared" else prepared.initial)

    def bent(graph, options):
        return GraphResult(perturb(graph.poses, 0.1, 0.02, seed=3), None, None, None, 0.0, "gtsam")

    monkeypatch.setattr(start_module.gtsam_solver, "optimize", bent)
    start = choose_start(prepared, OptimConfig(start="graph"), None, judge)
    assert start.name is StartKind.PREPARED and start.reason is StartReason.PLANES
    assert start.agreement_m2["graph"] > start.agreement_m2["prepared"]
    assert start.agreement_m2["graph"] > start.agreement_m2["prepared"]


def test_a_judge_with_no_shared_plane_leaves_the_choice_to_the_maps(prepared, sampler):
    """Scans whose frames share no plane (here: cells of one frame only) give the judge nothing (NaN): the start is
    chosen by map entropy, as without the dense stage, and the judge's empty verdict is kept in the report."""
    from dm2_backend.kernel.planes import Cells
    from dm2_backend.pipeline.dense_start import DenseCells

    rng = np.random.default_rng(0)
    lone = Cells(np.zeros(50, np.int32), np.full(50, 10, np.float32), rng.uniform(0, 1, (50, 3)).astype(np.float32),
                 np.zeros((50, 6), np.float32), 0.1)
    with pytest.warns(RuntimeWarning, match="Mean of empty slice"):
        start = choose_start(prepared, OptimConfig(start="graph"), sampler, DenseCells(lone, 0.4, None, 0.0))
    by_maps = choose_start(prepared, OptimConfig(start="graph"), sampler)
    assert start.name is by_maps.name and start.map_entropy == by_maps.map_entropy and start.map_entropy
    assert set(start.agreement_m2) == {"prepared", "graph"} and all(np.isnan(v) for v in start.agreement_m2.values())


def test_prepared_and_auto_on_planar_data(prepared, sampler):
    for name in ("prepared", "auto"):
        start = choose_start(prepared, OptimConfig(start=name), sampler)
        assert start.name is StartKind.PREPARED and start.poses is prepared.initial
    with pytest.raises(ValidationError, match="start"):  # a start that is none of the choices is never built
        OptimConfig(start="gtsam")


def test_the_dense_stage_on_planar_scans_stays_planar_and_lowers_the_error():
    """A 2D laser's lines are walls: the dense stage runs on planar scans, keeps x, y, yaw poses, leaves the truth
    at its noise floor and brings the loop-closed start to it."""
    from dm2_backend.pipeline.dense_start import dense_start
    from dm2_backend.pipeline.start import Start

    case = planar_case()
    seq = ScanSequence(lambda i: Scan(case.scans[i]), len(case.scans), planar=True)
    prep = Prepared(case.frames, case.warm, case.topology, case.pairwise)
    truth = dense_start(seq, prep, Start(case.gt, StartKind.PREPARED, "truth"), OptimConfig())
    floor = ate_rmse(case.gt, truth.poses)
    start = perturb(case.gt, 0.05, 0.01, seed=1)
    out = dense_start(seq, prep, Start(start, StartKind.PREPARED, "test"), OptimConfig())
    assert out.refined and len(out.dense.history) >= 1
    assert all(se3.is_planar(p) for p in out.poses)  # projected; before that the graph held them (test below)
    assert floor < 0.01  # the truth stands (its steps fit their frames best) or moves within the noise
    assert ate_rmse(case.gt, out.poses) < min(0.01, 0.2 * ate_rmse(case.gt, start))
    assert out.dense.step_guard.clean and truth.dense.step_guard.clean
    assert out.dense.stopped.reason in (StopReason.CONVERGED, StopReason.BUDGET)
    assert out.summary()["dense"]["stop_reason"] == out.dense.stopped.reason.value


def test_a_planar_graph_lifted_to_se3_has_the_planar_costs_and_optimum(prepared):
    """:meth:`PoseGraph.lifted_to_se3` keeps a planar graph: on planar poses its Pose3 factors cost what the Pose2
    ones do (noisy edges, so every information entry counts), GTSAM's Pose3 solution is the Pose2 one, and the
    measured odometry noise does not undo the hold."""
    from dm2_backend.optim import odometry_noise

    graph = build_graph(prepared.frames, perturb(prepared.initial, 0.2, 0.05, seed=2), prepared.topology,
                        prepared.pairwise)
    graph.relative = perturb(graph.relative, 0.05, 0.02, seed=4)
    lifted = graph.lifted_to_se3(1e6)
    assert lifted.information.shape[1:] == (6, 6) and not lifted.planar and graph.planar
    poses = perturb(graph.poses, 0.1, 0.03, seed=5)

    def cost(g) -> float:
        fg = gtsam_solver.factor_graph(g)  # no kernel: the plain weighted squares
        return fg.error(gtsam_solver.to_values(g, poses))

    assert cost(lifted) == pytest.approx(cost(graph), rel=1e-6)
    flat = gtsam_solver.optimize(graph, GRAPH_SOLVER).poses
    solved = gtsam_solver.optimize(lifted, GRAPH_SOLVER).poses
    np.testing.assert_allclose(se3.to_xy_yaw(solved), se3.to_xy_yaw(flat), atol=1e-4)
    steps = odometry_noise.consecutive_edges(lifted)
    noise = odometry_noise.MeasuredNoise(np.full(6, 0.01), np.zeros(6), len(steps))
    held = odometry_noise.reweighted(lifted, steps, noise).information[steps]
    assert np.all(held[:, [2, 3, 4], [2, 3, 4]] == 1e6) and np.all(held[:, [0, 1, 5], [0, 1, 5]] == 1e4)
    assert not np.any(held[:, 2, [0, 1, 5]])


def test_a_corridors_truth_holds_with_the_registrations_own_information():
    """A 2D laser in 2 m corridors (front half, 8 m range, 2 cm range noise): along a corridor the walls leave the
    position to the odometry and the registrations slide. The dense stage weighs each registration by its own
    point-to-line Hessian (free along the corridor) and sizes its voxels to the range noise: from the truth it
    stays closer than with isotropic information and the median-range voxel (0.048 m on this half lap)."""
    from optim_cases import frames_of

    from dm2_backend.kernel.planes import cells_from_scans
    from dm2_backend.optim.dense import refine_dense
    from dm2_backend.optim.derived import NOISE_WIDTHS, dense_voxel
    from dm2_backend.pipeline.dense_start import PLANAR_HOLD, dense_start, range_noise
    from dm2_backend.pipeline.start import Start
    from dm2_backend.plugins.registration_icp import IcpRegistration
    from dm2_backend.plugins.topology_radius import RadiusTopology
    from dm2_backend.simulate.corridor import corridor_sequence

    scans, gt, _ = corridor_sequence(laps=0.5)
    frames = frames_of(scans)
    topology = RadiusTopology().run(frames, gt)
    pairwise = IcpRegistration(progress=False).run(frames, gt, topology)
    assert pairwise.hessian is not None  # planar registrations record theirs
    prep = Prepared(frames, gt, topology, pairwise)
    noise = range_noise(prep)
    assert 0.005 < noise < 0.02  # the point-to-line spread of 2 cm range noise seen at an angle
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), planar=True)
    out = dense_start(seq, prep, Start(gt, StartKind.PREPARED, "truth"), OptimConfig())
    assert out.dense.returned is Kept.DENSE and out.dense.hessian_edges > 0
    voxel = dense_voxel(OptimConfig(), frames.scale)  # without the noise bound
    assert out.dense.voxel_m == pytest.approx(NOISE_WIDTHS * noise) and out.dense.voxel_m > voxel
    cells = cells_from_scans(seq, voxel / 4, 2048, 10**6, keep_scatter="thin", along_beams=False).extruded(voxel)
    isotropic = build_graph(frames, gt, topology, pairwise).lifted_to_se3(PLANAR_HOLD)
    before = refine_dense(cells, isotropic, gt, voxel, measure_odometry=True).poses
    assert ate_rmse(gt, out.poses) < 0.03 and ate_rmse(gt, out.poses) < 0.7 * ate_rmse(gt, before)


def test_every_start_can_be_what_the_dense_stages_judge_keeps():
    """The judge's candidates are the start (any kind) and the dense result: each start kind is a kept kind."""
    assert {k.value for k in StartKind} | {Kept.DENSE.value} == {k.value for k in Kept}
