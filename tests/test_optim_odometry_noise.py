"""The front end's odometry noise measured against a solution: the per-step sigma of a random walk recovered
through a solution with its own (larger) error, a finite weight for exact odometry, nothing measured from too
few edges, only the odometry edges reweighed; the dense stage that measures it, and its checkpoint."""

from __future__ import annotations

import json
from functools import lru_cache

import gtsam
import numpy as np
import pytest
from optim_cases import one_thread
from test_optim_dense import VOXEL, odometry_graph

from dm2_backend.kernel import planes
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import ROTATION_FIRST, PoseGraph
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.optim import dense_checkpoint, odometry_noise
from dm2_backend.optim.dense import refine_dense
from dm2_backend.optim.dense_round import Round
from dm2_backend.optim.stop import Stop, StopReason
from dm2_backend.pipeline.live import ate_rmse
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import SimSettings, simulate

#: a round record as the dense stage writes one
ROUND = Round(0, 1.0, 0.5, 0.5, 0.01, 10, 100, 0.001, 0.002, 0.001, 1.0, 1e-4, 5)

#: odometry noise per step (m, rad) and the solution's own error per frame, twice as large
SIGMA = np.array([5e-4, 5e-4, 2e-4, 5e-5, 5e-5, 1e-4])
SOLUTION = 2 * SIGMA


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def _perturbed(T: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``T`` times a random motion with per-component standard deviation ``sigma`` ([t, rotvec])."""
    xi = rng.normal(0.0, sigma, (len(T), 6))
    return T @ se3.make_poses(se3.exp_so3(xi[:, 3:]), xi[:, :3])


def _chain(frames: int, odometry: np.ndarray, solution: np.ndarray, seed: int = 0,
           loop: bool = False) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """A 2 cm-per-frame arc, its odometry edges (and one loop edge) with noise ``odometry``, and a solution
    with independent per-frame error ``solution``: the graph, the solution and the true poses."""
    rng = np.random.default_rng(seed)
    s = 0.02 * np.arange(frames)
    yaw = s / 15.0
    gt = se3.make_poses(se3.exp_so3(np.stack([0 * s, 0 * s, yaw], 1)),
                        np.stack([15 * np.sin(yaw), 15 * (1 - np.cos(yaw)), 0.1 * np.sin(s)], 1))
    relative = _perturbed(se3.relative(gt[:-1], gt[1:]), odometry, rng)
    edges = np.stack([np.arange(frames - 1), np.arange(1, frames)], 1)
    if loop:
        edges = np.concatenate([edges, [[0, frames - 1]]])
        relative = np.concatenate([relative, se3.relative(gt[:1], gt[-1:])])
    information = np.repeat(np.diag([1e4] * 3 + [1e6] * 3)[None], len(edges), 0)
    graph = PoseGraph(ids=np.arange(frames), poses=gt.copy(), edges=edges, relative=relative,
                      information=information, planar=False)
    return graph, _perturbed(gt, solution, rng), gt


def test_the_per_step_noise_of_a_random_walk_is_recovered_through_a_noisier_solution():
    graph, solution, _ = _chain(3000, SIGMA, SOLUTION)
    steps = odometry_noise.consecutive_edges(graph)
    noise = odometry_noise.estimate(graph, steps, solution)
    assert noise is not None and noise.edges == 2999
    np.testing.assert_allclose(noise.sigma, SIGMA, rtol=0.2)
    # the intercept is the solution's own error (both ends of a run of steps)
    np.testing.assert_allclose(noise.solution_sigma, np.sqrt(2) * SOLUTION, rtol=0.3)
    # the discrepancy of a perfect solution is the odometry's own error, step by step
    _, _, gt = _chain(3000, SIGMA, SOLUTION)
    exact = odometry_noise.discrepancies(graph.relative[steps], gt)
    np.testing.assert_allclose(exact.std(0), SIGMA, rtol=0.1)


def test_exact_odometry_gets_a_finite_weight():
    graph, solution, _ = _chain(500, np.zeros(6), SOLUTION)
    noise = odometry_noise.estimate(graph, odometry_noise.consecutive_edges(graph), solution)
    assert noise is not None
    assert np.all(noise.sigma >= odometry_noise.MIN_SIGMA) and np.all(noise.sigma < SOLUTION)
    assert np.all(np.isfinite(noise.information()))


@pytest.mark.parametrize("frames", [odometry_noise.MIN_EDGES, 10])
def test_too_few_edges_are_not_measured(frames):
    graph, solution, _ = _chain(frames, SIGMA, SOLUTION)  # MIN_EDGES frames: one edge short
    assert odometry_noise.estimate(graph, odometry_noise.consecutive_edges(graph), solution) is None


def test_a_chain_with_a_gap_is_not_measured():
    graph, solution, _ = _chain(400, SIGMA, SOLUTION)
    keep = np.delete(np.arange(len(graph.edges)), 200)  # the graph itself lacks the edge 200 -> 201
    gapped = PoseGraph(graph.ids, graph.poses, graph.edges[keep], graph.relative[keep], graph.information[keep])
    steps = odometry_noise.consecutive_edges(gapped)
    assert len(steps) == 398 and odometry_noise.estimate(gapped, steps, solution) is None


def test_the_discrepancy_is_gtsams_between_factor_error_in_g2o_order():
    graph, solution, _ = _chain(100, SIGMA, SOLUTION)
    mine = odometry_noise.discrepancies(graph.relative, solution)
    for i in (0, 37, 98):
        factor = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(graph.relative[i]),
                                          gtsam.noiseModel.Isotropic.Sigma(6, 1.0))
        theirs = factor.unwhitenedError(_values(solution[i], solution[i + 1]))  # rotation first
        # equal to first order: GTSAM's Logmap translation differs from ours by the rotation times the translation
        np.testing.assert_allclose(mine[i], theirs[ROTATION_FIRST.argsort()], atol=2e-6)
        assert np.abs(mine[i]).max() > 1e-4


def _values(a: np.ndarray, b: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(a))
    values.insert(1, gtsam.Pose3(b))
    return values


def test_only_the_odometry_edges_are_reweighed():
    graph, solution, _ = _chain(400, SIGMA, SOLUTION, loop=True)
    steps = odometry_noise.consecutive_edges(graph)
    np.testing.assert_array_equal(steps, np.arange(399))  # the loop edge is not a step
    noise = odometry_noise.estimate(graph, steps, solution)
    out = odometry_noise.reweighted(graph, steps, noise)
    np.testing.assert_array_equal(out.information[-1], graph.information[-1])
    np.testing.assert_allclose(out.information[0], np.diag(1.0 / noise.sigma**2))
    np.testing.assert_allclose(out.information[:399], np.diag(1.0 / noise.sigma**2)[None].repeat(399, 0))
    assert not np.allclose(graph.information[0], out.information[0])  # the input graph is left as it was
    np.testing.assert_array_equal(out.relative, graph.relative)


@lru_cache(maxsize=1)
def dense_street() -> tuple[planes.Cells, np.ndarray]:
    """150 frames 3 cm apart of the simulated 32-beam street (2 cm range noise), as cells, and the true poses."""
    scans, gt, _ = simulate(SimSettings(frames=150, seed=3, extent=10.0, laps=0.1), progress=False)
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), planar=False)
    return planes.cells_from_scans(seq, VOXEL / 4, 2048, 10**6), gt


def test_the_dense_stage_measures_the_odometry_it_was_given_with_a_guessed_weight(tmp_path):
    """Odometry 0.5 mm / 0.05 mrad a step, weighed as 2 cm / 1 mrad (the registrations' median, as
    ``build_graph`` guesses): the stage measures the true noise and keeps the truth's accuracy."""
    cells, gt = dense_street()
    graph, _ = odometry_graph(gt, 5e-4, 5e-5, seed=1)
    graph.information[:] = np.diag([1 / 0.02**2] * 3 + [1 / 0.001**2] * 3)
    start = gt.copy()
    start[:, :3, 3] += np.random.default_rng(4).normal(0, 0.005, (len(gt), 3))
    ckpt = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    result = refine_dense(cells, graph, start, VOXEL, measure_odometry=True, checkpoint=ckpt)
    assert result.odometry is not None and result.stopped.reason is StopReason.CONVERGED
    truth = np.array([5e-4] * 3 + [5e-5] * 3)
    assert np.all(result.odometry.sigma > truth / 2) and np.all(result.odometry.sigma < 2 * truth)
    assert ate_rmse(gt, result.poses) < 0.002  # from 0.0087; the range noise is 0.02 m
    assert sum(row.odometry_noise is not None for row in result.history) == 1
    # resumed after it ended: the measured noise comes back with it
    again = refine_dense(cells, graph, start, VOXEL, measure_odometry=True, checkpoint=ckpt, resume=True)
    np.testing.assert_array_equal(again.odometry.sigma, result.odometry.sigma)
    # interrupted in the round after the measurement and resumed: where the uninterrupted stage ends
    marked = next(i for i, row in enumerate(result.history) if row.odometry_noise is not None)
    assert marked + 1 < len(result.history)  # rounds ran with the measured weight
    calls = []

    def interrupt(_poses: np.ndarray) -> float:
        calls.append(1)
        if len(calls) == marked + 2:
            raise KeyboardInterrupt
        return 0.0

    ckpt.unlink()
    with pytest.raises(KeyboardInterrupt):
        refine_dense(cells, graph, start, VOXEL, trace=interrupt, checkpoint=ckpt, measure_odometry=True)
    assert dense_checkpoint.load(ckpt, start, 30).odometry is not None
    resumed = refine_dense(cells, graph, start, VOXEL, measure_odometry=True, checkpoint=ckpt, resume=True)
    assert resumed.stopped == result.stopped and len(resumed.history) == len(result.history)
    np.testing.assert_allclose(resumed.poses, result.poses, atol=1e-9)


def test_a_checkpoint_with_a_damaged_odometry_record_is_refused(tmp_path):
    poses = se3.identity(100)
    ckpt = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    row = ROUND
    good = odometry_noise.MeasuredNoise(SIGMA.copy(), SOLUTION.copy(), 99)
    dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [row], None, good), poses)
    np.testing.assert_array_equal(dense_checkpoint.load(ckpt, poses, 30).odometry.sigma, SIGMA)
    for bad, match in ((odometry_noise.MeasuredNoise(-SIGMA, SOLUTION, 99), "odometry noise"),
                       (odometry_noise.MeasuredNoise(SIGMA * 1e-200, SOLUTION, 99), "odometry noise"),
                       (odometry_noise.MeasuredNoise(SIGMA * 1e200, SOLUTION, 99), "odometry noise"),
                       (odometry_noise.MeasuredNoise(SIGMA, SOLUTION, 100), "odometry edges")):
        dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [row], None, bad), poses)
        with pytest.raises(InputError, match=match):
            dense_checkpoint.load(ckpt, poses, 30)
    for damaged in ({"sigma": 0.01}, {**ROUND.row(), "planes": 2.5}, {**ROUND.row(), "sigma": float("nan")}):
        dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [ROUND], None, good), poses)
        with np.load(ckpt) as data:
            meta = json.loads(str(data["meta"]))
            meta["history"] = [damaged]
            np.savez(ckpt.with_suffix(".tmp.npz"), poses=data["poses"], start=data["start"],
                     meta=np.array(json.dumps(meta)))
        ckpt.with_suffix(".tmp.npz").replace(ckpt)
        with pytest.raises(InputError, match="round records lack"):
            dense_checkpoint.load(ckpt, poses, 30)
    huge = odometry_noise.MeasuredNoise(SIGMA, SOLUTION, 99)
    dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [row], None, huge), poses)
    text = ckpt.read_bytes()
    with np.load(ckpt) as data:  # a sigma written as a 400-digit integer: too large for a float
        meta = json.loads(str(data["meta"]))
        meta["odometry"]["sigma"][0] = 10**400
        np.savez(ckpt.with_suffix(".tmp.npz"), poses=data["poses"], start=data["start"],
                 meta=np.array(json.dumps(meta)))
    ckpt.with_suffix(".tmp.npz").replace(ckpt)
    assert ckpt.read_bytes() != text
    with pytest.raises(InputError, match="does not fit"):
        dense_checkpoint.load(ckpt, poses, 30)


def test_a_checkpoint_records_why_the_stage_ended_and_refuses_an_unknown_reason(tmp_path):
    poses = se3.identity(10)
    ckpt = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    row = ROUND
    ended = Stop(StopReason.CONVERGED, "converged in round 0")
    dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [row], ended), poses)
    assert dense_checkpoint.load(ckpt, poses, 30).stopped == ended
    with np.load(ckpt) as data:
        meta = json.loads(str(data["meta"]))
        meta["stopped"]["reason"] = "bored"
        np.savez(ckpt.with_suffix(".tmp.npz"), poses=data["poses"], start=data["start"],
                 meta=np.array(json.dumps(meta)))
    ckpt.with_suffix(".tmp.npz").replace(ckpt)
    with pytest.raises(InputError, match="end record"):
        dense_checkpoint.load(ckpt, poses, 30)


@pytest.mark.parametrize("text,reason", [("converged in round 3 (rms step 0.0002 m)", StopReason.CONVERGED),
                                         ("round 4: no step lowered the objective", StopReason.NO_DESCENT),
                                         ("30 rounds", StopReason.BUDGET), ("", None)])
def test_an_earlier_dm2s_checkpoint_end_is_read_by_its_words(tmp_path, text, reason):
    poses = se3.identity(10)
    ckpt = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    row = ROUND
    dense_checkpoint.save(ckpt, dense_checkpoint.DenseState(poses, 1, 1e-4, [row]), poses)
    with np.load(ckpt) as data:
        meta = json.loads(str(data["meta"]))
        meta["stopped"] = text
        np.savez(ckpt.with_suffix(".tmp.npz"), poses=data["poses"], start=data["start"],
                 meta=np.array(json.dumps(meta)))
    ckpt.with_suffix(".tmp.npz").replace(ckpt)
    stopped = dense_checkpoint.load(ckpt, poses, 30).stopped
    assert (stopped is None) if reason is None else (stopped.reason is reason and stopped.detail == text)


def test_a_round_record_comes_back_from_its_row():
    noise = odometry_noise.MeasuredNoise(SIGMA.copy(), SOLUTION.copy(), 9)
    marked = Round(3, 2.0, 1.5, 0.5, 0.02, 7, 70, 0.001, 0.003, 0.002, 2.0, 1e-5, 9, ate=0.1, odometry_noise=noise)
    back = Round.of_row(marked.row(), 10)
    assert back.row() == marked.row() and Round.of_row(ROUND.row(), 10) == ROUND
    np.testing.assert_array_equal(back.odometry_noise.sigma, SIGMA)
    with pytest.raises(ValueError, match="odometry edges"):
        Round.of_row(marked.row(), 9)  # nine frames have eight steps
    assert "ate" not in ROUND.row() and "odometry_noise" not in ROUND.row()
