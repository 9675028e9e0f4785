"""Checks of an alignment between two scans: overlap both ways, free-space consistency (a false loop
puts walls where the other scan saw through) and how well the matched surfaces pin down translation."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter

from dm2_backend.algorithms.common import Cloud, Match
from dm2_backend.geometry import se3


def coverage(moving: Cloud, fixed: Cloud, T: np.ndarray, distance: float) -> tuple[float, float]:
    """Fraction of ``moving`` points, moved by ``T``, within ``distance`` of ``fixed`` points, and their
    rms distance (open3d's fitness and inlier rmse)."""
    if moving.planar:
        c, s = T[0, 0], T[1, 0]
        p = moving.xy @ np.array([[c, s], [-s, c]]) + T[:2, 3]
    else:
        p = se3.transform_points(T, moving.points)
    dist, _ = fixed.tree.query(p, distance_upper_bound=distance)
    ok = np.isfinite(dist)
    if not ok.any():
        return 0.0, float("inf")
    return float(ok.mean()), float(np.sqrt(np.mean(dist[ok] ** 2)))


def check_alignment(source: Cloud, target: Cloud, m: Match, distance: float, margin: float) -> float:
    """Tighten ``m.fitness`` to the smaller overlap of the two directions (a partial overlap must not
    pass on the smaller scan's side) and return the larger free-space violation of the two."""
    if m.fitness <= 0:
        return 1.0
    inv = se3.inverse(m.T)
    m.fitness = min(m.fitness, coverage(target, source, inv, distance)[0])
    return max(free_space(source, target, m.T, margin), free_space(target, source, inv, margin))


def free_space(source: Cloud, target: Cloud, T: np.ndarray, margin: float, bins: int = 360) -> float:
    """Fraction of ``source`` points, moved by ``T`` into the target's sensor frame, that lie more than
    ``margin`` in front of the target's returns along the same and the neighbouring bearings (and
    elevations): space the target sensor saw through. Near 0 for a true alignment; a false loop shows
    walls where the other scan saw free space. The neighbours' minimum keeps grazing walls, whose range
    changes fast with the bearing, from counting. Directions without a target return are not counted.
    Both clouds are scans in their sensor frames (the sensor at the origin), as :class:`Frames` holds them."""
    p = se3.transform_points(T, source.points)
    tgt = target.points
    r_p, r_t = np.linalg.norm(p, axis=1), np.linalg.norm(tgt, axis=1)
    az = lambda q: ((np.arctan2(q[:, 1], q[:, 0]) + np.pi) / (2 * np.pi) * bins).astype(int) % bins  # noqa: E731
    if source.planar:
        rows_p, rows_t, rows, keep = np.zeros(len(p), int), np.zeros(len(tgt), int), 1, np.ones(len(p), bool)
    else:
        el_t = np.arctan2(tgt[:, 2], np.hypot(tgt[:, 0], tgt[:, 1]))
        el_p = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
        lo, hi, rows = el_t.min(), el_t.max() + 1e-9, 16
        keep = (el_p >= lo) & (el_p < hi)
        rows_t = ((el_t - lo) / (hi - lo) * rows).astype(int)
        rows_p = np.clip(((el_p - lo) / (hi - lo) * rows).astype(int), 0, rows - 1)
    depth = np.full((rows, bins), np.inf)
    np.fmin.at(depth, (rows_t, az(tgt)), r_t)
    near = minimum_filter(depth, size=(min(rows, 3), 3), mode=("nearest", "wrap"))
    d = np.where(keep & np.isfinite(depth[rows_p, az(p)]), near[rows_p, az(p)], np.nan)
    known = np.isfinite(d)
    return float((r_p[known] < d[known] - margin).sum() / max(int(known.sum()), 1))


def constraint(source: Cloud, target: Cloud, T: np.ndarray, distance: float) -> float:
    """How well an alignment pins down translation: the smallest eigenvalue of the mean ``n n^T`` over
    the target normals of the correspondences within ``distance``. Near 0 in a featureless corridor
    (sliding along it costs nothing); up to 1/2 (2D) or 1/3 (3D) when walls face every way."""
    if source.planar:
        c, s = T[0, 0], T[1, 0]
        p = source.xy @ np.array([[c, s], [-s, c]]) + T[:2, 3]
        normals, tree = target.normals, target.tree
    else:
        p = se3.transform_points(T, source.points)
        normals, tree = target.normals, target.tree
    dist, idx = tree.query(p, distance_upper_bound=distance)
    ok = np.isfinite(dist)
    if ok.sum() < 3:
        return 0.0
    n = normals[idx[ok]]
    return float(np.linalg.eigvalsh(n.T @ n / len(n))[0])
