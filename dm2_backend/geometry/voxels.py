"""Grouping points by the voxel (or any integer key) they fall in."""

from __future__ import annotations

import numpy as np


def group_rows(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """The group id of each row of integer ``keys`` (K,3), numbered in the order of the keys, and the number of
    groups. One int64 per row where the keys' span allows it: a 1-D unique is about 7x faster than ``axis=0``."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), 0
    keys = keys - keys.min(0)
    dims = keys.max(0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        _, inverse = np.unique(np.ravel_multi_index(keys.T, dims), return_inverse=True)
    else:
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return inverse, int(inverse.max()) + 1
