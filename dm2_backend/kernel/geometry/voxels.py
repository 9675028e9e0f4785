"""Grouping points by the voxel (or any integer key) they fall in."""

from __future__ import annotations

import numpy as np


def flat_keys(keys: np.ndarray) -> np.ndarray | None:
    """Integer ``keys`` (K,D) as one int64 per row that sorts as the rows do (lexicographically), or None when
    their span does not fit in one (``keys`` not empty)."""
    # column by column: a reduction along axis 0 of (K,3), ``ravel_multi_index`` and the shifted copy cost more
    lo = [int(keys[:, a].min()) for a in range(keys.shape[1])]
    dims = [int(keys[:, a].max()) - lo[a] + 1 for a in range(keys.shape[1])]
    if float(np.prod(np.array(dims, np.float64))) >= 2.0**62:
        return None
    flat = keys[:, 0].astype(np.int64) - lo[0]
    for a in range(1, keys.shape[1]):
        flat = flat * dims[a] + (keys[:, a].astype(np.int64) - lo[a])
    return flat


def group_rows(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """The group id of each row of integer ``keys`` (K,3), numbered in the order of the keys, and the number of
    groups. One int64 per row where the keys' span allows it: a 1-D unique is several times faster than ``axis=0``."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), 0
    flat = flat_keys(keys)
    if flat is not None:
        _, inverse = np.unique(flat, return_inverse=True)
    else:
        _, inverse = np.unique(keys - keys.min(0), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return inverse, int(inverse.max()) + 1
