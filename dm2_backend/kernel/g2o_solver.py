"""Solve a :class:`PoseGraph` with the g2o optimiser (official ``g2opy`` bindings, extra ``dm2[g2o]``).

Levenberg with the Eigen sparse Cholesky solver; the first (or FIX) node is held fixed; iterations stop
when the relative chi2 gain falls below ``relative_error_tol`` (g2o's terminate action).

g2o's ``EdgeSE3`` measures rotation error as the quaternion vector part (about half the angle), while
dm2 graphs (and ``gtsam.readG2o``) hold tangent-space information; by default the rotation rows and
columns are scaled by 2 so that g2o minimises the same objective as GTSAM (``tangent_information=False``
keeps the file's numbers as g2o reads them). Errors are reported as 0.5 * chi2 (GTSAM's convention).
"""

from __future__ import annotations

import time

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.gtsam_solver import anchors
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.solver_options import KERNELS, GraphResult, SolverOptions
from dm2_backend.runtime.errors import InputError

_KERNEL_CLASSES = {"huber": "RobustKernelHuber", "cauchy": "RobustKernelCauchy", "tukey": "RobustKernelTukey",
                   "welsch": "RobustKernelWelsch", "geman-mcclure": "RobustKernelGemanMcClure",
                   "fair": "RobustKernelFair", "dcs": "RobustKernelDCS"}
assert set(_KERNEL_CLASSES) == set(KERNELS)
#: tangent (rad) -> quaternion-vector rotation error scale of g2o's EdgeSE3
_QUAT_SCALE = np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


def load_g2o():
    """The ``g2opy`` module, or :class:`InputError` telling how to install it."""
    try:
        import g2opy as g2o
    except ImportError:
        try:
            import g2o  # older builds of the same bindings
        except ImportError:
            raise InputError(None, "the g2o back-end needs g2opy: install dm2[g2o]") from None
    return g2o


def _build(g2o, graph: PoseGraph, options: SolverOptions, tangent_information: bool):
    opt = g2o.SparseOptimizer()
    if graph.planar:
        solver = g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())
    else:
        solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(solver))
    fixed = set(anchors(graph))
    xyt = se3.to_xy_yaw(graph.poses) if graph.planar else None
    for k, n in enumerate(graph.ids.tolist()):
        if graph.planar:
            v = g2o.VertexSE2()
            v.set_estimate(g2o.SE2(*xyt[k]))
        else:
            v = g2o.VertexSE3()
            v.set_estimate(g2o.Isometry3d(np.ascontiguousarray(graph.poses[k])))
        v.set_id(n)
        v.set_fixed(n in fixed)
        opt.add_vertex(v)
    kernel = getattr(g2o, _KERNEL_CLASSES[options.robust]) if options.robust else None
    z_xyt = se3.to_xy_yaw(graph.relative) if graph.planar else None
    for k, (i, j) in enumerate(graph.edges.tolist()):
        info = graph.information[k]
        if graph.planar:
            e = g2o.EdgeSE2()
            e.set_measurement(g2o.SE2(*z_xyt[k]))
        else:
            e = g2o.EdgeSE3()
            e.set_measurement(g2o.Isometry3d(np.ascontiguousarray(graph.relative[k])))
            if tangent_information:
                info = _QUAT_SCALE @ info @ _QUAT_SCALE
        e.set_vertex(0, opt.vertex(i))
        e.set_vertex(1, opt.vertex(j))
        e.set_information(np.ascontiguousarray(info))
        if kernel is not None:
            e.set_robust_kernel(kernel(options.kernel_k()))
        opt.add_edge(e)
    return opt


def _poses(g2o, graph: PoseGraph, opt) -> np.ndarray:
    if graph.planar:
        xyt = np.array([opt.vertex(n).estimate().to_vector() for n in graph.ids.tolist()])
        return se3.from_xy_yaw(xyt).reshape(-1, 4, 4)
    return np.stack([opt.vertex(n).estimate().matrix() for n in graph.ids.tolist()]).reshape(-1, 4, 4)


def optimize(graph: PoseGraph, options: SolverOptions | None = None, tangent_information: bool = True
             ) -> GraphResult:
    """Levenberg (g2o) from the graph's initial poses."""
    options = options or SolverOptions()
    options.check()
    g2o = load_g2o()
    t = time.perf_counter()
    opt = _build(g2o, graph, options, tangent_information)
    if not opt.initialize_optimization():
        raise InputError(graph.source, "g2o could not initialise the optimisation")
    opt.compute_active_errors()
    initial = 0.5 * opt.active_robust_chi2()
    stop = g2o.SparseOptimizerTerminateAction()
    stop.set_gain_threshold(options.relative_error_tol)
    stop.set_max_iterations(options.max_iterations)
    opt.add_post_iteration_action(stop)
    iterations = opt.optimize(options.max_iterations)
    if iterations < 0:
        raise InputError(graph.source, "g2o optimisation failed")
    opt.compute_active_errors()
    final = 0.5 * opt.active_robust_chi2()
    return GraphResult(
        poses=_poses(g2o, graph, opt), initial_error=float(initial), final_error=float(final),
        iterations=int(iterations), seconds=time.perf_counter() - t, solver="g2o",
        robust=options.robust, robust_k=options.kernel_k() if options.robust else None,
        anchored=tuple(anchors(graph)), tangent_information=tangent_information,
    )
