"""The pose-graph baselines as a table: a method's name -> the kernel's solver of that graph."""

from __future__ import annotations

from dm2_backend.kernel import g2o_solver, gtsam_solver
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.solver_options import GraphResult, SolverOptions
from dm2_backend.runtime.errors import InputError

#: one solver per name of ``methods.GRAPH_METHODS``
GRAPH_SOLVERS = {"gtsam": gtsam_solver.optimize, "g2o": g2o_solver.optimize}


def solve(method: str, graph: PoseGraph, options: SolverOptions) -> GraphResult:
    """Solve ``graph`` with the named solver."""
    if method not in GRAPH_SOLVERS:
        choices = " or ".join(GRAPH_SOLVERS)
        raise InputError(None, f"method {method!r} does not solve g2o graphs; use {choices}")
    return GRAPH_SOLVERS[method](graph, options)
