"""Checks of an alignment between two scans: overlap both ways, free-space consistency (a false loop
puts walls where the other scan saw through) and how well the matched surfaces pin down translation."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter

from dm2_backend.algorithms.common import Cloud, Match
from dm2_backend.kernel.geometry import se3


class Gate(enum.Enum):
    """A gate a pairwise registration must pass; its value formats the measured value and the limit it failed."""

    FITNESS = "fitness {value:.2f} < {limit:.2f}"
    RMSE = "rmse {value:.3f} > {limit:.3f}"
    FREE_SPACE = "free space {value:.2f} > {limit:.2f}"
    #: the loop-closure gates (``loops``, ``loops3d``): submap overlap, the correlative score (``loops``), the
    #: translation constraint, walls
    OVERLAP = "overlap {value:.2f} < {limit:.2f}"
    SCORE = "score {value:.2f} < {limit:.2f}"
    CORRIDOR = "constraint {value:.3f} < {limit:.3f} (degenerate: a corridor?)"
    DEGENERATE = "constraint {value:.3f} < {limit:.3f} (degenerate)"
    WALLS = "free space {value:.2f} > {limit:.2f} (walls where the other saw none)"

    def message(self, value: float, limit: float) -> str:
        return self.value.format(value=value, limit=limit)


@dataclass(frozen=True)
class GateFailure:
    """One failed gate: what it measured and the limit."""

    gate: Gate
    value: float
    limit: float

    def __str__(self) -> str:
        return self.gate.message(self.value, self.limit)


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
    r_p = np.linalg.norm(p, axis=1)
    image = depth_image(target, bins)
    if source.planar:
        rows_p, keep = np.zeros(len(p), int), np.ones(len(p), bool)
    else:
        el_p = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
        keep = (el_p >= image.lo) & (el_p < image.hi)
        rows_p = np.clip(((el_p - image.lo) / (image.hi - image.lo) * image.rows).astype(int), 0, image.rows - 1)
    col_p = _bearing_bin(p, bins)
    d = np.where(keep & np.isfinite(image.depth[rows_p, col_p]), image.near[rows_p, col_p], np.nan)
    known = np.isfinite(d)
    return float((r_p[known] < d[known] - margin).sum() / max(int(known.sum()), 1))


@dataclass(frozen=True)
class DepthImage:
    """A scan's nearest return per (elevation row, bearing bin) and the minimum over each cell's neighbours;
    ``lo``/``hi`` the elevation span of the rows (3D)."""

    depth: np.ndarray
    near: np.ndarray
    rows: int
    lo: float = 0.0
    hi: float = 0.0


def depth_image(cloud: Cloud, bins: int) -> DepthImage:
    """The cloud's :class:`DepthImage`, made once and kept with it (each frame is the target of several
    pairs: about a third of the 3D pairwise registration time went into remaking it)."""
    key = ("depth_image", bins)
    if key not in cloud.derived:
        pts = cloud.points
        r = np.linalg.norm(pts, axis=1)
        if cloud.planar:
            rows, lo, hi, row = 1, 0.0, 0.0, np.zeros(len(pts), int)
        else:
            el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))
            lo, hi, rows = float(el.min()), float(el.max()) + 1e-9, 16
            row = ((el - lo) / (hi - lo) * rows).astype(int)
        depth = np.full((rows, bins), np.inf)
        np.fmin.at(depth, (row, _bearing_bin(pts, bins)), r)
        near = minimum_filter(depth, size=(min(rows, 3), 3), mode=("nearest", "wrap"))
        cloud.derived[key] = DepthImage(depth, near, rows, lo, hi)
    return cloud.derived[key]


def _bearing_bin(q: np.ndarray, bins: int) -> np.ndarray:
    return ((np.arctan2(q[:, 1], q[:, 0]) + np.pi) / (2 * np.pi) * bins).astype(int) % bins


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


def plane_residuals(source: Cloud, target: Cloud, T: np.ndarray, distance: float) -> np.ndarray:
    """Point-to-plane (planar: point-to-line) residual (m) of each ``source`` point placed at ``T`` against its
    nearest ``target`` point's plane; NaN where no target point lies within ``distance``."""
    moved = se3.transform_points(T, source.points)
    query = moved[:, :2] if source.planar else moved
    dist, idx = target.tree.query(query, distance_upper_bound=distance)
    ok = np.isfinite(dist)
    out = np.full(len(query), np.nan)
    gap = query[ok] - (target.xy if target.planar else target.points)[idx[ok]]
    out[ok] = np.einsum("ij,ij->i", target.normals[idx[ok]], gap)
    return out


def truncated_squares(residuals: np.ndarray, distance: float) -> np.ndarray:
    """Squared residuals truncated at ``distance``; a point without a match (NaN) costs ``distance`` squared."""
    return np.minimum(np.nan_to_num(np.abs(residuals), nan=distance), distance) ** 2


#: one-sided z of :func:`significantly_worse` (a chance of 1 in 2,000 that equally good poses are told apart)
Z_WORSE = 3.29
#: the fewest points matched at the better pose for :func:`significantly_worse` to tell anything
MIN_MATCHED = 10


def significantly_worse(source: Cloud, target: Cloud, worse: np.ndarray, better: np.ndarray, distance: float) -> bool:
    """Whether ``source`` placed at ``worse`` fits ``target`` worse than at ``better``, beyond chance: over the
    points matched at ``better``, their squared residuals at ``worse`` (truncated at ``distance``: a point that
    lost its match costs that much) exceed those at ``better`` by a paired one-sided test at :data:`Z_WORSE`.
    The test takes the residuals' scatter from the points themselves, so sampling and surface roughness, which
    dwarf the sensor's noise on sparse scans, are not taken for evidence."""
    b = plane_residuals(source, target, better, distance)
    on = np.isfinite(b)
    if on.sum() < MIN_MATCHED:
        return False
    d = truncated_squares(plane_residuals(source, target, worse, distance)[on], distance) - b[on] ** 2
    spread = float(np.std(d, ddof=1))
    return bool(np.mean(d) > Z_WORSE * spread / np.sqrt(len(d))) if spread > 0 else bool(np.mean(d) > 0)
