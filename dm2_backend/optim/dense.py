"""Second-order steps over all poses at once: the dense plane term jointly with the pose graph's factors.

The objective is DeepMapping2's geometric part in second-order form: the dense multi-frame term
(:mod:`dm2_backend.kernel.planes`, every scan point against planes shared by many frames) plus the
local-to-global consistency with the pairwise registrations and the front end's odometry, which are the pose
graph's between factors (``dm2 baseline gtsam``'s graph, Cauchy kernel, the first pose held). Each round
assigns the cells to planes at the current poses (with their robust weights, as in iteratively reweighted least
squares), fits the planes, and takes one damped Gauss-Newton step over every pose at once with the planes
eliminated (their 3x3 blocks: a Schur complement, solved by conjugate gradients preconditioned with the sparse
planes-held system of GTSAM's linearised factors and each frame's 6x6 plane block), so frames that share a plane
move together (holding the planes crept along the trajectory's soft modes) and what the scans do not constrain
(a camera facing one wall) stays where the registrations put it. A line search on the objective with the planes
fitted again scales the step; a round is taken only when it lowers that objective. Once the planes settle,
the front end's odometry edges (which the graph weighs by a guess) can be weighed by their own noise
measured against that solution (:mod:`dm2_backend.optim.odometry_noise`), and the rounds go on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import gtsam
import numpy as np
from scipy.sparse import bsr_matrix, coo_matrix, csr_matrix
from scipy.sparse.linalg import LinearOperator, cg, splu

from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel import planes as plane_term
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.planes import Cells
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.solver_options import SolverOptions
from dm2_backend.optim import dense_checkpoint, odometry_noise
from dm2_backend.optim.dense_round import Round
from dm2_backend.optim.stop import Stop, StopReason
from dm2_backend.runtime.memory import release_freed_memory
from dm2_backend.runtime.progress import progress as progress_of

log = logging.getLogger(__name__)

#: the graph's factors as ``dm2 baseline gtsam`` solves them
GRAPH_SOLVER = SolverOptions(robust="cauchy")
#: step scales tried in turn along each Gauss-Newton step while the objective keeps falling; the last that lowered
#: it is taken
SCALES = (1.0, 2.0, 4.0)
#: with ``measure_odometry``, the odometry's noise is measured once the map's noise scale changes by less than
#: this fraction of itself in a round (or the rounds converge, whichever comes first)
SETTLED = 0.01


@dataclass(frozen=True)
class DenseResult:
    """The dense stage's poses, its rounds and why they ended."""

    poses: np.ndarray
    #: one record per round: objective (plane, graph, total), noise sigma (m), planes, step (m, rad), step scale
    history: list[Round] = field(default_factory=list)
    seconds: float = 0.0
    stopped: Stop = Stop(StopReason.BUDGET, "")
    #: rounds a checkpoint had done before this run continued it (0: started afresh)
    resumed_after: int = 0
    #: the odometry noise measured once the planes settled and weighed from then on (None: not measured)
    odometry: odometry_noise.MeasuredNoise | None = None


def _step(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Root-mean-square and largest translation (m), largest rotation (rad) between two pose sets."""
    moved = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    angle = se3.rotation_angle(se3.relative(a, b)[:, :3, :3])
    return (float(np.sqrt(np.mean(moved**2))) if len(moved) else 0.0, float(np.max(moved, initial=0.0)),
            float(np.max(angle, initial=0.0)))


class _Objective:
    """Plane term (planes fitted to the poses) + the graph's factors, in GTSAM's units (half the squares)."""

    def __init__(self, fg: gtsam.NonlinearFactorGraph, graph: PoseGraph) -> None:
        self.fg, self.graph = fg, graph

    def __call__(self, assignment: plane_term.Assignment, values: gtsam.Values) -> tuple[float, float, np.ndarray]:
        poses = gtsam_solver.from_values(self.graph, values)
        plane = 0.5 * plane_term.cost(assignment, poses)
        return plane + self.fg.error(values), plane, poses


def _graph_system(lin: gtsam.GaussianFactorGraph, keys: np.ndarray) -> tuple[csr_matrix, np.ndarray]:
    """The linearised graph factors as a sparse Hessian J^T J (6N x 6N, in the order of the ascending ``keys``)
    and gradient (N,6)."""
    frames = len(keys)
    rows, cols, vals = lin.sparseJacobian_()  # float64 triplets, 1-indexed (kept lean: 7 M of them at 20,000 frames)
    shape = (int(rows.max()), 6 * frames)
    keep = np.flatnonzero(cols <= 6 * frames)  # the last column (6N + 1) holds the right-hand side b
    vals = vals[keep]
    rows, cols = rows[keep].astype(np.int32), cols[keep].astype(np.int32)
    rows -= 1
    cols -= 1
    del keep
    covered = int(np.count_nonzero(np.bincount(cols, minlength=6 * frames)))
    if covered != 6 * frames:  # every pose is in a factor (the prior holds the first)
        raise ValueError(f"the graph's linear system covers {covered} of {6 * frames} columns")
    J = coo_matrix((vals, (rows, cols)), shape=shape).tocsr()
    del rows, cols, vals
    grad = lin.gradientAtZero()
    return (J.T @ J).tocsr(), np.stack([grad.at(int(k)) for k in keys])


def _solve(Hg: csr_matrix, gg: np.ndarray, plane: plane_term.Linear, lam: float, tol: float = 1e-3,
           max_iter: int = 200) -> tuple[np.ndarray, int]:
    """The damped Gauss-Newton step of graph + plane term with the planes eliminated, by conjugate gradients
    preconditioned with the planes-held system (a sparse factorisation). Returns the step (N,6), iterations."""
    n = len(gg)
    blocks = bsr_matrix((plane.H, np.arange(n), np.arange(n + 1)), shape=(6 * n, 6 * n))
    held = Hg + blocks
    diagonal = held.diagonal()
    held.setdiag(diagonal + (lam * diagonal + 1e-12))  # in place: every diagonal entry is stored (6x6 blocks)
    held = held.tocsc()
    factor = splu(held)
    reduced = LinearOperator(held.shape, matvec=lambda x: held @ x - plane.coupling(x), dtype=np.float64)
    iterations = [0]

    def count(_x: np.ndarray) -> None:
        iterations[0] += 1

    step, info = cg(reduced, plane.rhs() - gg.ravel(), rtol=tol, maxiter=max_iter,
                    M=LinearOperator(held.shape, matvec=factor.solve, dtype=np.float64), callback=count)
    if info != 0:  # the line search still judges the step; say that it is inexact
        log.debug("conjugate gradients stopped after %d iterations short of %g", iterations[0], tol)
    return step.reshape(n, 6), iterations[0]


def _vector_values(ids: np.ndarray, step: np.ndarray) -> gtsam.VectorValues:
    out = gtsam.VectorValues()
    for key, x in zip(ids.tolist(), step, strict=True):
        out.insert(int(key), x)
    return out


def refine_dense(cells: Cells, graph: PoseGraph, start: np.ndarray, voxel: float, rounds: int = 30,
                 tolerance: float = 0.05, progress: bool = False,
                 trace: Callable[[np.ndarray], float] | None = None, checkpoint: Path | None = None,
                 resume: bool = False, measure_odometry: bool = False) -> DenseResult:
    """Poses minimising plane term + graph factors from ``start``; stops when a round moves the poses by less
    than ``tolerance`` noise sigmas (root mean square: a cell changing voxel moves a frame or two a little every
    round; once the odometry is reweighed, when the graph factors' cost changes by less than ``tolerance`` of
    itself), after ``rounds`` rounds, or when no step lowers the objective. ``trace``:
    accuracy against ground truth, recorded per round (never used to
    decide). ``checkpoint``: the state is written there after every round; with ``resume`` the stage continues
    from the state found there (:mod:`dm2_backend.optim.dense_checkpoint`), or returns it when it had ended.
    ``measure_odometry``: once the planes settle (:func:`_settled`), the rounds converge or no step improves,
    whichever comes first, with a round left, the odometry edges (frame i to i+1) are weighed by their noise
    measured against the poses there, and the rounds go on."""
    t0 = time.perf_counter()
    start = np.asarray(start, dtype=np.float64)
    state = dense_checkpoint.DenseState(start.copy(), 0, 1e-4, [])
    if resume and checkpoint is not None and checkpoint.is_file():
        state = dense_checkpoint.load(checkpoint, start, rounds)
        log.info("dense stage: resumed after round %d of %d%s", state.rounds_done, rounds,
                 f" ({state.stopped})" if state.stopped is not None else "")
        if state.stopped is not None:
            return DenseResult(state.poses, state.history, 0.0, state.stopped, state.rounds_done, state.odometry)
    odometry = state.odometry
    steps = odometry_noise.consecutive_edges(graph) if measure_odometry or odometry is not None else None
    if odometry is not None:
        graph = odometry_noise.reweighted(graph, steps, odometry)
    fg = gtsam_solver.factor_graph(graph, GRAPH_SOLVER)
    objective = _Objective(fg, graph)
    poses, history, lam = state.poses, state.history, state.damping
    values = gtsam_solver.to_values(graph, poses)
    stopped = Stop(StopReason.BUDGET, f"{rounds} rounds")

    def keep(rounds_done: int, end: Stop | None = None) -> None:
        if checkpoint is not None:
            dense_checkpoint.save(checkpoint, dense_checkpoint.DenseState(poses, rounds_done, lam, history, end,
                                                                          odometry), start)

    def reweigh(rounds_done: int) -> bool:
        """At a minimum with the guessed odometry weight: weigh the odometry edges by their noise measured at
        the current poses and go on (once; False: not asked for, done, or too few edges)."""
        nonlocal odometry, graph, fg, objective, values, lam
        if not measure_odometry or odometry is not None or not history or rounds_done >= rounds:
            return False  # measured once, against a round's poses, with a round left to use it
        odometry = odometry_noise.estimate(graph, steps, poses)
        if odometry is None:
            return False
        graph, fg, objective, values = _reweighed(graph, steps, odometry, poses)
        history[-1] = replace(history[-1], odometry_noise=odometry)
        lam = 1e-4
        keep(rounds_done)
        return True

    bar = progress_of(range(state.rounds_done, rounds), "dense", unit="round", enabled=progress)
    for r in bar:
        release_freed_memory()  # the preparation's and the last round's freed blocks: each round peaks alone
        assignment = plane_term.assign(cells, poses, voxel)
        plane = plane_term.linearise(assignment, plane_term.fit(assignment, poses), poses)
        current, _, _ = objective(assignment, values)
        Hg, gg = _graph_system(fg.linearize(values), graph.ids)
        best, iterations = None, 0
        for _ in range(8):
            step, iterations = _solve(Hg, gg, plane, lam)
            delta = _vector_values(graph.ids, step)
            for scale in SCALES:
                trial = values.retract(delta.scale(scale))
                value, plane_value, trial_poses = objective(assignment, trial)
                if value < (best[0] if best else current):
                    best = (value, plane_value, trial, trial_poses, scale)
                elif best is not None:
                    break
            if best is not None:
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if best is None:
            if reweigh(r + 1):
                continue
            stopped = Stop(StopReason.NO_DESCENT, f"round {r}: no step lowered the objective")
            keep(r + 1, stopped)
            break
        value, plane_value, values, new_poses, scale = best
        step_rms, step_t, step_r = _step(poses, new_poses)
        poses = new_poses
        history.append(Round(r, value, plane_value, value - plane_value, assignment.sigma, int(assignment.voxels),
                             int(assignment.cells), step_rms, step_t, step_r, scale, lam, int(iterations),
                             ate=float(trace(poses)) if trace is not None else None))
        bar.set_postfix(objective=f"{value:.6g}", sigma=f"{assignment.sigma:.3g}", step=f"{step_rms:.2g}")
        done = _converged(history, tolerance)
        if (done or _settled(history)) and reweigh(r + 1):
            assignment = plane = None
            continue
        if done:
            stopped = Stop(StopReason.CONVERGED, f"converged in round {r} (rms step {step_rms:.2g} m" + (
                ", odometry weighed by its measured noise)" if odometry is not None else ")"))
            keep(r + 1, stopped)
            break
        keep(r + 1, stopped if r + 1 == rounds else None)
        assignment = plane = None  # released before the next round builds its own
    log.debug("dense stage: %s, %.1f s", stopped, time.perf_counter() - t0)
    return DenseResult(poses, history, time.perf_counter() - t0, stopped, state.rounds_done, odometry)


def _converged(history: list[Round], tolerance: float) -> bool:
    """The last round moved the poses by less than ``tolerance`` noise sigmas; once the odometry is reweighed
    (the rounds after the one that holds ``odometry_noise``), also the graph factors' cost changed by less than
    ``tolerance`` of itself between two rounds: the new weights move what the odometry holds by steps below the
    first test that still improve the steps, and the graph's cost alone can settle while the poses still move
    (docs/decisions/0007-odometry-noise-measured.md)."""
    if history[-1].step_rms_m >= tolerance * history[-1].sigma:
        return False
    marks = [i for i, row in enumerate(history) if row.odometry_noise is not None]
    if not marks:
        return True
    after = history[marks[0] + 1:]
    return len(after) >= 2 and abs(after[-1].graph - after[-2].graph) < tolerance * after[-2].graph


def _settled(history: list[Round]) -> bool:
    """The map's noise scale changed by less than :data:`SETTLED` of itself over the last round: the planes are
    as sharp as the current weights make them, though frames may still jitter between cells (a short sequence
    whose odometry is weighed too weakly can alternate between two states and never pass the step test)."""
    return len(history) >= 2 and abs(history[-1].sigma - history[-2].sigma) < SETTLED * history[-2].sigma


def _reweighed(graph: PoseGraph, steps: np.ndarray, noise: odometry_noise.MeasuredNoise, poses: np.ndarray
               ) -> tuple[PoseGraph, gtsam.NonlinearFactorGraph, _Objective, gtsam.Values]:
    """The graph with its odometry ``steps`` weighed by ``noise``, its factors, objective and values at ``poses``."""
    log.info("dense stage: odometry noise per step %s (m, rad; the graph had guessed %s)",
             " ".join(f"{v:.2g}" for v in noise.sigma),
             " ".join(f"{v:.2g}" for v in 1.0 / np.sqrt(np.diag(graph.information[steps[0]]))))
    graph = odometry_noise.reweighted(graph, steps, noise)
    fg = gtsam_solver.factor_graph(graph, GRAPH_SOLVER)
    return graph, fg, _Objective(fg, graph), gtsam_solver.to_values(graph, poses)
