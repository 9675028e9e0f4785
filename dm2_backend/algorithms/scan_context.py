"""Scan Context (Kim & Kim 2018) place descriptors: a polar grid (rings x sectors) around the sensor
holding the highest point per cell for 3D scans, or cell occupancy for planar laser scans; the
ring key (occupancy per ring) is rotation invariant, the distance searches all column shifts."""

from __future__ import annotations

import numpy as np


def descriptor(points: np.ndarray, rings: int, sectors: int, max_range: float, planar: bool) -> np.ndarray:
    """(rings, sectors) descriptor of one scan in its sensor frame."""
    p = np.asarray(points, dtype=np.float64)
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (r > 0) & (r < max_range)
    p, r = p[keep], r[keep]
    desc = np.zeros((rings, sectors))
    if len(p) == 0:
        return desc
    ring = np.minimum((r / max_range * rings).astype(int), rings - 1)
    sector = ((np.arctan2(p[:, 1], p[:, 0]) % (2 * np.pi)) / (2 * np.pi) * sectors).astype(int) % sectors
    if planar:
        desc[ring, sector] = 1.0
    else:
        height = p[:, 2] - np.percentile(p[:, 2], 1) + 1e-3  # above the scan's floor, occupied cells > 0
        np.maximum.at(desc, (ring, sector), np.maximum(height, 1e-3))
    return desc


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Rotation-invariant key: the occupied fraction of each ring."""
    return (desc > 0).mean(axis=-1)


def distance(query: np.ndarray, candidate: np.ndarray) -> tuple[float, int]:
    """Scan Context distance (1 - mean cosine of the columns both occupy) minimised over column shifts,
    and the best shift s: the candidate rolled by s columns matches the query, i.e. the candidate's yaw
    relative to the query is ``s * 2 pi / sectors``."""
    sectors = query.shape[1]
    qn, cn = np.linalg.norm(query, axis=0), np.linalg.norm(candidate, axis=0)
    qu = np.divide(query, qn, out=np.zeros_like(query), where=qn > 0)
    cu = np.divide(candidate, cn, out=np.zeros_like(candidate), where=cn > 0)
    dots = qu.T @ cu  # dots[a, b] = column a of query . column b of candidate
    col = np.arange(sectors)
    shifted = (col[None, :] - col[:, None]) % sectors  # [s, c] -> candidate column c - s
    sims = dots[col[None, :], shifted].sum(axis=1)
    both = ((qn > 0)[None, :] & (cn > 0)[shifted]).sum(axis=1)
    dist = np.where(both > 0, 1.0 - sims / np.maximum(both, 1), 1.0)
    s = int(np.argmin(dist))
    return float(dist[s]), s
