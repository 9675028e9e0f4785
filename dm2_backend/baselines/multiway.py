"""Open3D multiway registration: an ``o3d.pipelines.registration.PoseGraph`` of odometry edges (certain) and
loop edges (uncertain, pruned by the line process), information matrices from the point clouds, solved by
``global_optimization`` (Levenberg-Marquardt), node 0 as reference.

Edges use the same transforms as :func:`dm2_backend.kernel.graph_edges.build_graph`; an Open3D edge
(source j, target i) holds ``T_j^i`` (maps frame j's points into frame i).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from dm2_backend.algorithms.common import fine_distance, lengths, repeatable_registration
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.graph_edges import valid_pairs
from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.kernel.solver_options import GraphResult, SolverOptions
from dm2_backend.runtime.errors import InputError

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class MultiwayResult(GraphResult):
    """Open3D's answer (no errors or iterations reported) and its settings: the correspondence distance (m), the
    line process's prune threshold, and the edges (odometry, how many from the warm start; loop edges
    given and kept)."""

    max_correspondence_distance: float = 0.0
    edge_prune_threshold: float = 0.0
    odometry_edges: int = 0
    odometry_from_warm_start: int = 0
    loop_edges: int = 0
    loop_edges_kept: int = 0

    def settings(self) -> dict:
        return {"max_correspondence_distance": self.max_correspondence_distance,
                "edge_prune_threshold": self.edge_prune_threshold, "odometry_edges": self.odometry_edges,
                "odometry_from_warm_start": self.odometry_from_warm_start, "loop_edges": self.loop_edges,
                "loop_edges_kept": self.loop_edges_kept}


def dense_bytes(nodes: int) -> int:
    """Memory of the dense (6N x 6N, float64) normal matrix that Open3D's global_optimization builds."""
    return 8 * (6 * nodes) ** 2


def available_memory() -> int:
    """Bytes available to a new allocation: MemAvailable (free plus reclaimable cache) where Linux has it."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_size(nodes: int, available: int | None = None) -> None:
    """Refuse graphs whose dense system would not fit in half the available memory (ACES, 7,374 nodes,
    needs 15.7 GB), with a clear error instead of an out-of-memory kill."""
    available = available if available is not None else available_memory()
    need = dense_bytes(nodes)
    if need > available // 2:
        raise InputError(None, f"multiway: Open3D's global optimisation builds a dense {6 * nodes} x {6 * nodes} "
                               f"system ({need / 2**30:.1f} GiB for {nodes} frames, {available / 2**30:.1f} GiB "
                               "available); use gtsam or g2o for sequences this long")


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def multiway(frames: Frames, warm: np.ndarray, topology: Topology, pairwise: Pairwise,
             options: SolverOptions | None = None, edge_prune_threshold: float = 0.25) -> GraphResult:
    """Optimised poses (N,4,4); ``max_correspondence_distance`` = 3 point spacings (or voxels)."""
    options = options or SolverOptions()
    check_size(len(warm))
    t = time.perf_counter()
    distance = fine_distance(lengths(frames))
    clouds = [_cloud(p) for p in frames.points]
    pairs = valid_pairs(topology, pairwise, frames)
    graph = reg.PoseGraph()
    for T in warm:
        graph.nodes.append(reg.PoseGraphNode(np.asarray(T, dtype=np.float64)))

    def add(i: int, j: int, T: np.ndarray, uncertain: bool) -> None:
        info = reg.get_information_matrix_from_point_clouds(clouds[j], clouds[i], distance, T)
        graph.edges.append(reg.PoseGraphEdge(j, i, T, info, uncertain=uncertain))

    from_warm = 0
    loops = sorted(p for p in pairs if p[1] - p[0] > 1)
    criteria = reg.GlobalOptimizationConvergenceCriteria()
    criteria.max_iteration = options.max_iterations
    criteria.min_relative_residual_increment = options.relative_error_tol
    option = reg.GlobalOptimizationOption(max_correspondence_distance=distance,
                                          edge_prune_threshold=edge_prune_threshold, reference_node=0)
    # open3d's sums on one thread: the same graph and answer every run
    with repeatable_registration(), o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        for i in range(len(warm) - 1):
            e = pairs.get((i, i + 1))
            if e is None:
                from_warm += 1
            add(i, i + 1, e.relative if e is not None else se3.relative(warm[i], warm[i + 1]), False)
        for a, b in loops:
            add(a, b, pairs[(a, b)].relative, True)
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
    poses = np.stack([np.asarray(node.pose) for node in graph.nodes]).reshape(-1, 4, 4)
    if frames.planar:
        poses = se3.from_xy_yaw(se3.to_xy_yaw(poses)).reshape(-1, 4, 4)
    kept = len(graph.edges) - (len(warm) - 1)
    return MultiwayResult(
        poses=poses, initial_error=None, final_error=None, iterations=None, seconds=time.perf_counter() - t,
        solver="open3d multiway", max_correspondence_distance=distance, edge_prune_threshold=edge_prune_threshold,
        odometry_edges=len(warm) - 1, odometry_from_warm_start=from_warm, loop_edges=len(loops),
        loop_edges_kept=kept,
    )
