"""Pairwise registration of a topology's pairs, the machinery of the registration plugins (``icp``, ``gicp``,
``small-gicp``): each neighbour registered onto its anchor, initialised from the warm-start relative pose
inv(T_i) @ T_j (or from the loop transform the ``descriptor`` topology verified), gated on fitness and inlier
rmse; pairs failing a gate are marked invalid, keep their initial relative pose and get a reason. A plugin
chooses how a frame's cloud is built and how one pair is registered (``_check``, ``_build``, ``_register_pair``).

Each unordered pair is registered once (the reverse direction is its inverse). Pairs run in order, a chunk
at a time; a frame's cloud (normals or covariances, KD-tree) is built when a chunk needs it and dropped when
the next chunk does not, so memory stays bounded however long the sequence (all clouds at once took about
150 KB per 3D frame: 1.5 GB at 10,000 frames); a frame of a loop pair is built again at most once per chunk
that needs it. Planar pairs run on a thread pool (scipy's KD-tree releases the GIL; open3d parallelises each
3D ICP itself).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import numpy as np

from dm2_backend.algorithms.common import (
    Cloud,
    Match,
    fine_distance,
    lengths,
    orthonormal,
    project_planar,
    repeatable_registration,
    resolve_method,
)
from dm2_backend.algorithms.gates import Gate, GateFailure, check_alignment
from dm2_backend.algorithms.icp import register
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames, FramesPart, Pairwise, Topology
from dm2_backend.runtime import cluster
from dm2_backend.runtime.progress import progress

#: the coarse pass's correspondence distance, in fine distances: the farthest a registration reaches for a
#: correspondence, and so the scale of a step's error where it slid into a wrong local minimum (a tolerance, not a
#: bound: along a direction the scans leave free ICP can slide further over its iterations)
COARSE = 4.0


@dataclass
class PairwiseRegistration:
    """Options; None means derived from the data (``Frames.scale``). By itself: open3d ICP (GICP in 3D, 2D
    point-to-line for planar scans, by default)."""

    name: ClassVar[str] = "pairwise"

    #: "auto" (GICP in 3D, 2D point-to-line for planar scans), "point-to-plane", "point-to-point", "gicp"
    method: str = "auto"
    #: fine correspondence distance (m); default 3 point spacings; a coarse pass at :data:`COARSE` times it runs
    #: first where the fine pass alone ends below 0.8 fitness
    max_distance: float | None = None
    #: gates: overlap (the smaller of the two directions' fractions of points with a correspondence);
    #: inlier rmse (m; default 1.5 point spacings; correspondences spread evenly up to the 3-spacing
    #: distance give 1.7); free space (fraction of either scan's points lying more than
    #: ``free_space_margin`` (m) in front of what the other measured along the same bearing; defaults:
    #: planar 0.15 with 4 fine correspondence distances, 3D 0.1 with one)
    min_fitness: float = 0.5
    #: rmse gate: largest inlier rmse of a registration (m); default 1.5 point spacings
    max_rmse: float | None = None
    #: free-space gate: largest fraction of either scan's points in space the other saw through; default 0.15
    #: for planar scans, 0.1 in 3D
    max_free_space: float | None = None
    #: a point counts as in free space this far in front of the other scan's return or more (m); default 4 fine
    #: correspondence distances for planar scans, one in 3D
    free_space_margin: float | None = None
    #: at most this many ICP iterations per correspondence-distance pass (open3d and the planar ICP; small-gicp
    #: keeps its own limit)
    iterations: int = 30
    #: planar point-to-line: Cauchy reweighting of the residuals with this threshold in robust standard
    #: deviations (0: plain least squares; see ``icp.icp_2d``): plain least squares leaves an along-track bias
    #: that, summed over thousands of consecutive pairs, bends the pose graph
    #: (docs/decisions/0009-registration-and-pose-graph-defaults.md)
    robust_k: float = 2.3849
    #: 3D: a pass stops when fitness and inlier rmse change by less than this fraction (open3d's usual 1e-6 gives
    #: the same relative poses in more time; docs/decisions/0009-registration-and-pose-graph-defaults.md)
    tolerance: float = 1e-4
    #: pairs per chunk (the clouds of at most two chunks are held at once, so memory stays linear; a frame's cloud
    #: is built again when a later chunk needs it; docs/decisions/0009-registration-and-pose-graph-defaults.md)
    chunk: int = 1024
    #: each registration's information for the pose graph: "isotropic" (from its rmse, overlap and points;
    #: see ``kernel.graph_edges``) or "hessian" (its own point-to-plane, planar: point-to-line, Gauss-Newton Hessian
    #: over its correspondences over the variance of those residuals, ``Pairwise.hessian``: a direction the
    #: matched geometry leaves free, along a corridor or across the one wall a camera sees, gets no weight).
    #: Isotropic by default: the pose graphs end no better with the Hessians
    #: (docs/decisions/0009-registration-and-pose-graph-defaults.md). The odometry edges keep the median
    #: isotropic weight either way. Planar scans with
    #: ``method: point-to-point`` give no Hessian (their edges stay isotropic). This is the pose graphs' choice
    #: (``dm2 baseline``, the 3D start); planar registrations record their Hessian either way and the dense stage
    #: weighs by it wherever one was recorded
    information: Literal["hessian", "isotropic"] = "isotropic"
    #: start loop pairs from the transform the descriptor topology verified
    use_loops: bool = True
    #: threads over pairs; default: the CPU count (at most 8; each open3d registration on one thread, as the
    #: preparation runs it: ``common.repeatable_registration``)
    workers: int | None = None
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, poses: np.ndarray, topology: Topology) -> Pairwise:
        self._check(frames)
        # a planar match's point-to-line Hessian comes with its fit (the dense stage weighs by it); a 3D one costs
        # a normal estimate, made when the pose graph asks for it
        self._record_hessians = self.information == "hessian" or frames.planar
        scale = lengths(frames)
        fine = self.max_distance or fine_distance(scale)
        max_rmse = self.max_rmse or 1.5 * max(scale.voxel, scale.spacing)
        margin = self.free_space_margin or (4.0 if frames.planar else 1.0) * fine
        max_free = self.max_free_space or (0.15 if frames.planar else 0.1)
        groups = np.asarray(topology.groups)
        n, k = groups.shape
        rows, cols = np.nonzero(groups >= 0)
        anchors, neighbours = rows.tolist(), groups[rows, cols].tolist()
        pairs = sorted({(min(i, j), max(i, j)) for i, j in zip(anchors, neighbours, strict=True)})
        inits = self._inits(poses, pairs, topology)
        engine = cluster.current()
        if engine is not None and pairs:
            results = self._on_cluster(engine, frames, pairs, inits, fine, margin)
        else:
            # pairs side by side, each on one thread (docs/decisions/0019-repeatable-registration.md)
            workers = self.workers or min(8, os.cpu_count() or 1)
            with repeatable_registration():
                results = self._matches(frames, pairs, inits, fine, margin, workers, self.progress)
        relative, valid = np.tile(np.eye(4), (n, k, 1, 1)), np.zeros((n, k), bool)
        fitness, rmse, reason = np.zeros((n, k)), np.full((n, k), np.inf), {}
        hessian = plane_rmse = None
        if self._record_hessians:
            dim = 3 if frames.planar else 6
            hessian, plane_rmse = np.zeros((n, k, dim, dim), np.float32), np.full((n, k), np.inf)
        by_pair: dict[tuple[int, int], tuple[np.ndarray, list[GateFailure], Match]] = {}
        for pair, (m, free) in zip(pairs, results, strict=True):
            failed = []
            if m.fitness < self.min_fitness:
                failed.append(GateFailure(Gate.FITNESS, m.fitness, self.min_fitness))
            if m.rmse > max_rmse:
                failed.append(GateFailure(Gate.RMSE, m.rmse, max_rmse))
            if free > max_free:
                failed.append(GateFailure(Gate.FREE_SPACE, free, max_free))
            T = m.T if not failed else inits[pair]
            by_pair[pair] = (project_planar(T) if frames.planar else orthonormal(T), failed, m)
        for i in range(n):
            for col in range(k):
                j = int(groups[i, col])
                if j < 0:
                    continue
                pair = (min(i, j), max(i, j))
                T, failed, m = by_pair[pair]
                relative[i, col] = T if i < j else se3.inverse(T)
                valid[i, col], fitness[i, col], rmse[i, col] = not failed, m.fitness, m.rmse
                if hessian is not None and m.hessian is not None:
                    hessian[i, col], plane_rmse[i, col] = m.hessian, m.plane_rmse
                if failed:
                    reason[(i, j)] = "; ".join(map(str, failed))
        return Pairwise(relative, valid, fitness, rmse, reason, hessian, plane_rmse)

    def _matches(self, frames: Frames, pairs: list[tuple[int, int]], inits: dict, fine: float, margin: float,
                 workers: int, shown: bool) -> list[tuple[Match, float]]:
        """Each pair's match and the share of its points in the other's free space, in order, on ``workers``
        threads."""
        with ThreadPoolExecutor(workers) as pool:

            def job(pair: tuple[int, int]) -> tuple[Match, float]:
                a, b = pair
                m = self._register_pair(frames, a, b, inits[pair], fine)
                return m, check_alignment(self._clouds[b], self._clouds[a], m, fine, margin)

            jobs = self._chunked(frames, pairs, fine, pool, job)
            results = list(progress(jobs, "pairwise icp", total=len(pairs), unit="pair", enabled=shown))
        self._clouds = {}
        return results

    def _on_cluster(self, engine: cluster.Engine, frames: Frames, pairs: list[tuple[int, int]], inits: dict,
                    fine: float, margin: float) -> list[tuple[Match, float]]:
        """:meth:`_matches` of consecutive runs of pairs as tasks on the cluster's workers (at least four a
        worker thread, at most :attr:`chunk` pairs each), each reading its frames where they are stored."""
        size = engine.run_length(len(pairs), largest=self.chunk)
        light = replace(self)  # the options, not the clouds in hand (open3d clouds do not pickle)
        light._record_hessians = self._record_hessians
        tasks = []
        for c0 in range(0, len(pairs), size):
            part = pairs[c0 : c0 + size]
            tasks.append(PairTask(light, frames.part(np.array(part).ravel()), part, [inits[p] for p in part], fine,
                                  margin))
        done = engine.map(register_pairs, tasks, "pairwise icp", unit="task", enabled=self.progress)
        return [match for chunk in done for match in chunk]

    def _check(self, frames: Frames) -> None:
        self._method = resolve_method(self.method, frames.planar)

    def _chunked(self, frames: Frames, pairs: list[tuple[int, int]], fine: float, pool: ThreadPoolExecutor, job):
        """``job`` of every pair, in order, a chunk at a time: the clouds a chunk needs are built before it
        (those the chunk before it left are kept) and only the ones the next chunk needs are kept after it."""
        self._clouds = {}
        size = max(1, self.chunk)
        for c0 in range(0, len(pairs), size):
            part = pairs[c0 : c0 + size]
            need = sorted({f for p in part for f in p})
            missing = [f for f in need if f not in self._clouds]
            self._clouds.update(zip(missing, self._build(frames, missing, fine, pool), strict=True))
            yield from pool.map(job, part)
            keep = {f for p in pairs[c0 + size : c0 + 2 * size] for f in p}
            self._clouds = {f: c for f, c in self._clouds.items() if f in keep}

    def _build(self, frames: Frames, used: list[int], fine: float, pool: ThreadPoolExecutor) -> list:
        """Each of these frames' clouds (normals, KD-tree), built on the pool."""
        method = self._method
        # a 3D point-to-point match's Hessian needs the target's normals: built here, not by two pairs at once
        normals = self._record_hessians and method == "point-to-point" and not frames.planar

        def build(f: int) -> Cloud:
            cloud = Cloud(frames.points[f], frames.planar, 2.0 * fine).ensure(method)
            return cloud.ensure("point-to-plane") if normals else cloud

        return list(pool.map(build, used))

    def _register_pair(self, frames: Frames, a: int, b: int, init: np.ndarray, fine: float) -> Match:
        """Frame b onto frame a from init: T_b^a with its fitness and rmse. A good initial guess (most
        pairs) converges in the fine pass alone; otherwise a coarse pass runs first."""
        src, tgt = self._clouds[b], self._clouds[a]
        kw = {"tolerance": self.tolerance, "robust_k": self.robust_k, "hessian": self._record_hessians}
        m = register(src, tgt, init, (fine,), self._method, self.iterations, **kw)
        if m.fitness >= 0.8:
            return m
        return register(src, tgt, init, (COARSE * fine, fine), self._method, self.iterations, **kw)

    def _inits(self, poses: np.ndarray, pairs: list[tuple[int, int]], topology: Topology) -> dict:
        """T_b^a for each pair (a < b): the verified loop transform if any, else inv(T_a) @ T_b."""
        loops: dict[tuple[int, int], np.ndarray] = {}
        if self.use_loops:
            for e in topology.log:
                if e.get("accepted") and "relative" in e:
                    i, j, T = int(e["i"]), int(e["j"]), np.asarray(e["relative"], dtype=np.float64)
                    loops[(min(i, j), max(i, j))] = T if i < j else se3.inverse(T)
        return {p: loops.get(p, se3.relative(poses[p[0]], poses[p[1]])) for p in pairs}


@dataclass(frozen=True)
class PairTask:
    """Pairs for one worker: the registration (its options), the frames they need, each pair's start, the fine
    correspondence distance and the free-space margin."""

    registration: PairwiseRegistration
    frames: FramesPart
    pairs: list[tuple[int, int]]
    inits: list[np.ndarray]
    fine: float
    margin: float


def register_pairs(task: PairTask) -> list[tuple[Match, float]]:
    """A worker's run of :meth:`PairwiseRegistration._matches` on one thread (open3d's too)."""
    registration, frames = task.registration, task.frames.frames()
    registration._check(frames)
    inits = dict(zip(task.pairs, task.inits, strict=True))
    with repeatable_registration():
        return registration._matches(frames, task.pairs, inits, task.fine, task.margin, 1, False)
