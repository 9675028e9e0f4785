"""Keyframes along a trajectory and the local submaps around them, as bird's-eye 2D point sets.

A keyframe is placed every ``spacing`` metres of travel (or ``angle`` of turn); its submap gathers the
scans within ``half_length`` metres of path on either side, moved into the keyframe's frame with the
(locally accurate) input poses, so matching uses a few metres of structure instead of one scan. A submap keeps only
points that another of its points supports (lies within ``support``): a surface is seen by several beams or scans,
a spurious return (an isolated long return through glass or an open door) by one, and scattered points that match
nothing would otherwise let many different alignments score alike.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.algorithms.common import path_length
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames


def select(poses: np.ndarray, spacing: float, angle: float) -> np.ndarray:
    """Indices of keyframes: the first pose, then each pose ``spacing`` m or ``angle`` rad from the last."""
    yaw = se3.to_xy_yaw(poses)[:, 2]
    path = path_length(poses)
    keep = [0]
    for i in range(1, len(poses)):
        turn = abs(se3.wrap_angle(yaw[i] - yaw[keep[-1]]))
        if path[i] - path[keep[-1]] >= spacing or turn >= angle:
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


def bird_eye(points: np.ndarray, planar: bool) -> np.ndarray:
    """(M, 2) x, y of a scan; 3D scans drop their lowest fifth in height (the ground)."""
    if planar or len(points) == 0:
        return points[:, :2].astype(np.float64)
    z = points[:, 2]
    return points[z > np.percentile(z, 20), :2].astype(np.float64)


def first_per_cell(xy: np.ndarray, cell: float) -> np.ndarray:
    """Indices (sorted) of the first point in each ``cell`` x ``cell`` grid cell."""
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    _, first = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_index=True)
    return np.sort(first)


def thin(xy: np.ndarray, cell: float, limit: int, rng: np.random.Generator) -> np.ndarray:
    """One point per ``cell`` grid cell, then at most ``limit`` points (random subset)."""
    if len(xy) == 0:
        return xy
    xy = xy[first_per_cell(xy, cell)]
    if len(xy) > limit:
        xy = xy[np.sort(rng.choice(len(xy), limit, replace=False))]
    return xy


def supported(xy: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points with another point within ``radius`` (all of them when ``radius`` is 0)."""
    if radius <= 0 or len(xy) < 2:
        return np.ones(len(xy), dtype=bool)
    d = cKDTree(xy).query(xy, k=2, distance_upper_bound=radius)[0][:, 1]
    return np.isfinite(d)


def origins(poses: np.ndarray, path: np.ndarray, key: int, half_length: float) -> np.ndarray:
    """(F, 2) sensor positions of the scans of frame ``key``'s submap (see :func:`submap`), in its frame: where
    that visit could see from."""
    lo, hi = np.searchsorted(path, [path[key] - half_length, path[key] + half_length], side="left")
    rel = se3.inverse(poses[key]) @ poses[lo : min(hi + 1, len(poses))]
    return rel[:, :2, 3].astype(np.float64)


def submap(frames: Frames, poses: np.ndarray, path: np.ndarray, key: int, half_length: float,
           cell: float, support: float = 0.0) -> np.ndarray:
    """Bird's-eye points of the scans within ``half_length`` of path around frame ``key``, in its frame, one per
    ``cell``, those without another within ``support`` dropped (:func:`supported`)."""
    lo, hi = np.searchsorted(path, [path[key] - half_length, path[key] + half_length], side="left")
    inv = se3.inverse(poses[key])
    parts = []
    for f in range(lo, min(hi + 1, len(poses))):
        rel = inv @ poses[f]
        xy = bird_eye(frames.points[f], frames.planar)
        parts.append(xy @ rel[:2, :2].T + rel[:2, 3])
    xy = np.concatenate(parts) if parts else np.zeros((0, 2))
    if not len(xy):
        return xy
    xy = xy[first_per_cell(xy, cell)]
    return xy[supported(xy, support)]
