"""The front end's odometry noise, measured against a solution the scans pin (the dense stage's first pass).

The pose graph gives every odometry edge one guessed weight (:mod:`dm2_backend.kernel.graph_edges`: the median
registration information); on a dense sequence that is far weaker than the odometry is, and the plane term's
per-frame jitter then shows between consecutive frames. The odometry's own noise can be read off the data.
Against a solution ``P``, edge ``i`` (frame i to i+1, measured ``Z_i``) has the discrepancy
``e_i = [t, log R]`` of ``inv(Z_i) inv(P_i) P_{i+1}`` (its between factor's error, g2o order): the odometry's
error of that step minus the change of the solution's error between the two frames. Summed over ``k``
consecutive steps, the odometry's errors add up (variance ``k sigma^2``: the random walk a chain of between
factors models) while the solution's telescope to the difference of two frames' errors (a variance that does
not grow with ``k``; nearly so for short steps, as on the dense sequences where the weight matters: each
frame's rotation error times the step's length and rotation is left over and adds to the slope).
So the variance of the k-step sums, regressed on ``k``, has the odometry's per-step
variance as its slope and the solution's as its intercept, per component.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import PoseGraph

#: the longest run of steps summed (k = 1 .. WINDOW): long enough to tell the slope from the intercept, short
#: enough that a drifting solution's error still looks constant over it
WINDOW = 8
#: the fewest odometry edges to estimate from (below that the graph keeps its weights;
#: docs/decisions/0007-odometry-noise-measured.md)
MIN_EDGES = 10 * WINDOW
#: the smallest and largest per-step standard deviation taken (m or rad): exact odometry still gets a finite
#: weight, odometry that says nothing a non-zero one
MIN_SIGMA = 1e-6
MAX_SIGMA = 1e3


@dataclass(eq=False)
class MeasuredNoise:
    """The odometry edges' noise measured against a solution (not the planar warm start's translation and yaw
    spread, ``drift_windows.OdometryNoise``): per-step standard deviation (g2o order ``[x y z rx ry rz]``, m and
    rad, on the right of the measured step: the tangent of GTSAM's BetweenFactor error), the solution's own error
    scale (the intercept, same units), and the edges measured."""

    sigma: np.ndarray
    solution_sigma: np.ndarray
    edges: int

    def information(self) -> np.ndarray:
        return np.diag(1.0 / self.sigma**2)

    def summary(self) -> dict:
        return {"sigma": self.sigma.tolist(), "solution_sigma": self.solution_sigma.tolist(), "edges": self.edges}

    @classmethod
    def of_summary(cls, record: object, frames: int) -> MeasuredNoise:
        """A :meth:`summary` read back from a checkpoint: six sigmas within what :func:`estimate` gives, six
        finite non-negative solution sigmas, and an edge count below the ``frames`` (ValueError)."""
        if not isinstance(record, dict):
            raise ValueError("its odometry noise is not a mapping")
        sigma = np.asarray(record.get("sigma"), dtype=np.float64)
        solution = np.asarray(record.get("solution_sigma"), dtype=np.float64)
        edges = record.get("edges")
        if sigma.shape != (6,) or not np.all((sigma >= MIN_SIGMA) & (sigma <= MAX_SIGMA)):
            raise ValueError(f"its odometry noise is not six numbers from {MIN_SIGMA:g} to {MAX_SIGMA:g}")
        if solution.shape != (6,) or not np.all(np.isfinite(solution) & (solution >= 0)):
            raise ValueError("its solution noise is not six numbers")
        if isinstance(edges, bool) or not isinstance(edges, int) or not 0 < edges < frames:
            raise ValueError(f"its odometry edges {edges!r}, not 1 to {frames - 1}")
        return cls(sigma, solution, edges)


def discrepancies(relative: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(E,6) ``[t, log R]`` of ``inv(relative[i]) inv(poses[i]) poses[i+1]`` for consecutive frames."""
    d = se3.relative(relative, se3.relative(poses[:-1], poses[1:]))
    return np.concatenate([d[:, :3, 3], se3.log_so3(d[:, :3, :3])], 1)


def _robust_variance(x: np.ndarray) -> np.ndarray:
    """Per column: the squared normal-consistent median absolute deviation."""
    return (1.4826 * np.median(np.abs(x - np.median(x, 0)), 0)) ** 2


def estimate(graph: PoseGraph, edges: np.ndarray, poses: np.ndarray) -> MeasuredNoise | None:
    """The per-step noise of the graph's odometry ``edges`` (frame i to i+1 for every i, in order) against the
    solution ``poses``, or None with fewer than :data:`MIN_EDGES` of them. A slope that the data do not tell
    from zero is taken at its standard error (never an infinite weight)."""
    if len(edges) < MIN_EDGES or len(edges) != len(poses) - 1:
        return None
    e = discrepancies(graph.relative[edges], poses)
    sums = np.concatenate([np.zeros((1, 6)), np.cumsum(e, 0)])
    k = np.arange(1, WINDOW + 1)
    variance = np.stack([_robust_variance(sums[w:] - sums[:-w]) for w in k])
    design = np.stack([np.ones(WINDOW), k.astype(np.float64)], 1)
    coef, *_ = np.linalg.lstsq(design, variance, rcond=None)
    resid = variance - design @ coef
    dof = WINDOW - 2
    slope_var = (resid**2).sum(0) / dof * np.linalg.inv(design.T @ design)[1, 1]
    slope = np.maximum(coef[1], np.sqrt(slope_var))
    sigma = np.clip(np.sqrt(np.maximum(slope, 0.0)), MIN_SIGMA, MAX_SIGMA)
    return MeasuredNoise(sigma, np.sqrt(np.maximum(coef[0], 0.0)), len(edges))


def consecutive_edges(graph: PoseGraph) -> np.ndarray:
    """Indices of the graph's edges from node row i to i+1, ordered by i (one each)."""
    rows = graph.edge_rows()
    steps = np.flatnonzero(rows[:, 1] - rows[:, 0] == 1)
    _, first = np.unique(rows[steps, 0], return_index=True)
    return steps[first]


def reweighted(graph: PoseGraph, edges: np.ndarray, noise: MeasuredNoise) -> PoseGraph:
    """A copy of ``graph`` whose ``edges`` carry the information of ``noise``; the axes a lifted planar graph holds
    (``held``, :meth:`~dm2_backend.kernel.pose_graph.PoseGraph.lifted_to_se3`) keep their hold."""
    information = graph.information.copy()
    measured = noise.information()
    if graph.held is not None:
        axes = np.asarray(graph.held.axes)
        measured = measured.copy()
        measured[axes, :] = 0.0
        measured[:, axes] = 0.0
        measured[axes, axes] = graph.held.information
    information[edges] = measured
    return replace(graph, information=information)
