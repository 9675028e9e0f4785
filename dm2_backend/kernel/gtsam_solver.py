"""Solve a :class:`PoseGraph` with GTSAM: Pose3 / Pose2 between factors, a prior on the first (or FIX)
node, optional robust kernel, Levenberg-Marquardt."""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph, indefinite
from dm2_backend.kernel.solver_options import KERNELS, GraphResult, SolverOptions
from dm2_backend.runtime.errors import InputError

#: robust kernel name -> GTSAM m-estimator
ESTIMATORS = {
    "huber": gtsam.noiseModel.mEstimator.Huber,
    "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
    "tukey": gtsam.noiseModel.mEstimator.Tukey,
    "welsch": gtsam.noiseModel.mEstimator.Welsch,
    "geman-mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
    "fair": gtsam.noiseModel.mEstimator.Fair,
    "dcs": gtsam.noiseModel.mEstimator.DCS,
}
assert set(ESTIMATORS) == set(KERNELS)

log = logging.getLogger(__name__)


def components(graph: PoseGraph) -> np.ndarray:
    """Connected-component label of each node (graph order)."""
    rows = graph.edge_rows()
    n = len(graph)
    adjacency = coo_matrix((np.ones(len(rows)), (rows[:, 0], rows[:, 1])), shape=(n, n))
    return connected_components(adjacency, directed=False)[1]


def anchors(graph: PoseGraph) -> list[int]:
    """Node ids held at their initial pose (prior / fixed): the FIX nodes, else the first node; plus the
    first node of every connected component without one (its placement is otherwise undetermined)."""
    labels = components(graph)
    held = [int(n) for n in graph.fixed] if graph.fixed else [int(graph.ids[0])]
    index = graph.index_of()
    covered = {int(labels[index[n]]) for n in held}
    for row in range(len(graph)):
        if int(labels[row]) not in covered:
            covered.add(int(labels[row]))
            held.append(int(graph.ids[row]))
    return held


def to_values(graph: PoseGraph, poses: np.ndarray | None = None) -> gtsam.Values:
    values = gtsam.Values()
    poses = graph.poses if poses is None else poses
    if graph.planar:
        for n, (x, y, th) in zip(graph.ids.tolist(), se3.to_xy_yaw(poses).tolist(), strict=True):
            values.insert(n, gtsam.Pose2(x, y, th))
    else:
        for n, T in zip(graph.ids.tolist(), poses, strict=True):
            values.insert(n, gtsam.Pose3(T))
    return values


def from_values(graph: PoseGraph, values: gtsam.Values) -> np.ndarray:
    if graph.planar:
        xyt = np.array([[p.x(), p.y(), p.theta()] for p in (values.atPose2(n) for n in graph.ids.tolist())])
        return se3.from_xy_yaw(xyt).reshape(-1, 4, 4)
    return np.stack([values.atPose3(n).matrix() for n in graph.ids.tolist()]).reshape(-1, 4, 4)


def factor_graph(graph: PoseGraph, options: SolverOptions | None = None) -> gtsam.NonlinearFactorGraph:
    """Between factors (information in GTSAM's rotation-first order; the robust kernel on every edge but the
    graph's ``exact`` ones) plus the anchor prior."""
    options = options or SolverOptions()
    options.check()
    fg = gtsam.NonlinearFactorGraph()
    info = graph.information_rotation_first()
    index = graph.index_of()
    dim = 3 if graph.planar else 6
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.full(dim, options.prior_sigma))
    for n in anchors(graph):
        T = graph.poses[index[n]]
        if graph.planar:
            fg.add(gtsam.PriorFactorPose2(n, gtsam.Pose2(*se3.to_xy_yaw(T)), prior))
        else:
            fg.add(gtsam.PriorFactorPose3(n, gtsam.Pose3(T), prior))
    robust = ESTIMATORS[options.robust].Create(options.kernel_k()) if options.robust else None
    exact = graph.exact if graph.exact is not None else np.zeros(len(graph.edges), bool)
    for (i, j), Z, omega, as_given in zip(graph.edges.tolist(), graph.relative, info, exact, strict=True):
        noise = gtsam.noiseModel.Gaussian.Information(omega)
        if robust is not None and not as_given:
            noise = gtsam.noiseModel.Robust.Create(robust, noise)
        if graph.planar:
            fg.add(gtsam.BetweenFactorPose2(i, j, gtsam.Pose2(*se3.to_xy_yaw(Z)), noise))
        else:
            fg.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(Z), noise))
    return fg


def lm_params(options: SolverOptions) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_error_tol)
    return params


def warn_indefinite(graph: PoseGraph) -> int:
    """One warning when information matrices are not positive semi-definite: GTSAM weighs them as
    ``gtsam.readG2o`` does (by the Cholesky factor Eigen returns for each, which for such a matrix is not a
    square root of it), which is the answer a user asking for GTSAM's gets. Returns how many."""
    bad = indefinite(graph.information)
    if bad.any():
        first = graph.edges[int(np.argmax(bad))].tolist()
        log.warning("%s: %d of %d information matrices are not positive semi-definite (first: edge %d-%d); GTSAM "
                    "weighs the file as given, as gtsam.readG2o does (a partial Cholesky factor of each; "
                    "--information nearest-psd: the nearest positive-definite ones)",
                    graph.source or "graph", int(bad.sum()), len(bad), *first)
    return int(bad.sum())


def _check_finite(graph: PoseGraph, fg: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> None:
    """Refuse (one line) a graph whose GTSAM error is not finite at the start: an information matrix that is
    diagonal with a negative entry gets NaN sigmas in GTSAM (the file's matrix is at fault, not the poses,
    which the reader checked)."""
    if np.isfinite(fg.error(initial)):
        return
    offset = fg.size() - len(graph.edges)  # the anchor priors come first
    bad = [k for k in range(len(graph.edges)) if not np.isfinite(fg.at(offset + k).error(initial))]
    where = f" (first: edge {graph.edges[bad[0], 0]}-{graph.edges[bad[0], 1]})" if bad else ""
    raise InputError(graph.source, f"GTSAM's error is not finite on {len(bad)} edges{where}: an "
                     "information matrix with a negative diagonal entry gets NaN sigmas in GTSAM; --information "
                     "nearest-psd uses the nearest positive-definite ones")


def optimize(graph: PoseGraph, options: SolverOptions | None = None) -> GraphResult:
    """Levenberg-Marquardt from the graph's initial poses. Information matrices that are not positive
    semi-definite are weighed as GTSAM weighs them (one warning, :func:`warn_indefinite`), unless that
    makes the error NaN (refused, one line)."""
    options = options or SolverOptions()
    warn_indefinite(graph)
    t = time.perf_counter()
    fg = factor_graph(graph, options)
    initial = to_values(graph)
    _check_finite(graph, fg, initial)
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(fg, initial, lm_params(options))
        result = optimizer.optimize()
    except RuntimeError as exc:  # indeterminate system: a disconnected or degenerate graph
        why = str(exc).strip().splitlines()[0]
        raise InputError(graph.source, f"GTSAM could not solve the graph: {why}") from exc
    return GraphResult(
        poses=from_values(graph, result), initial_error=float(fg.error(initial)),
        final_error=float(fg.error(result)), iterations=int(optimizer.iterations()),
        seconds=time.perf_counter() - t, solver="gtsam",
        robust=options.robust, robust_k=options.kernel_k() if options.robust else None,
        anchored=tuple(anchors(graph)),
    )
