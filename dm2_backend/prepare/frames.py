"""Load and down-sample scans into :class:`Frames`, and derive the data's length scales."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import open3d as o3d

from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.scan_scale import derive_scale, point_spacing
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.runtime.threads import ordered_map


def downsample(points: np.ndarray, voxel: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Voxel-grid down-sample (open3d), then cap the count by random sampling."""
    return cap(voxel_grid(points, voxel, max_points), max_points, rng)


def voxel_grid(points: np.ndarray, voxel: float, max_points: int) -> np.ndarray:
    """The centroid of each occupied voxel (open3d), when there are more than ``max_points`` points."""
    if voxel > 0 and len(points) > max_points:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
        points = np.asarray(pcd.voxel_down_sample(voxel).points, dtype=np.float32)
    return points


def cap(points: np.ndarray, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``max_points`` of the points, a random subset in their order (float32, contiguous)."""
    if len(points) > max_points:
        points = points[np.sort(rng.choice(len(points), max_points, replace=False))]
    return np.ascontiguousarray(points, dtype=np.float32)


def load_frames(
    seq: ScanSequence,
    max_points: int,
    voxel: float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> Frames:
    """Down-sample every scan. ``voxel`` defaults to ``range_median / 40`` (3D) or no voxel grid (planar)."""
    scale = derive_scale(seq)
    if voxel is None:
        voxel = 0.0 if seq.planar else scale.range_median / 40.0
    rng = np.random.default_rng(seed)
    scans = progress_of(seq, "load scans", total=len(seq), unit="scan", enabled=progress)
    # the voxel grids on threads while the next scans are read; the random caps in order, as one loop draws them
    points = [cap(p, max_points, rng) for p in ordered_map(lambda s: voxel_grid(s.points, voxel, max_points), scans)]
    sub = points[:: max(1, len(points) // 20)]
    scale = replace(scale, voxel=float(voxel), spacing=float(np.median([point_spacing(p) for p in sub])))
    return Frames(points=points, timestamps=seq.timestamps, planar=seq.planar, scale=scale)


def motion_per_frame(poses: np.ndarray) -> float:
    """Median translation between consecutive poses."""
    if len(poses) < 2:
        return 0.0
    return float(np.median(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)))
