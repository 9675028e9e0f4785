"""Batch organisation: which frames share a group with each anchor (the paper's Sec. 3.3)."""

from __future__ import annotations

import numpy as np


def temporal_groups(n: int, k: int) -> np.ndarray:
    """Each anchor with its k nearest frames in time (DeepMapping's sequential batches)."""
    offsets = np.array(sorted(range(-k, k + 1), key=lambda o: (abs(o), o))[1 : k + 1])
    idx = np.arange(n)[:, None] + offsets[None, :]
    return np.where((idx >= 0) & (idx < n), idx, -1)


def random_groups(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """Each anchor with k random other frames (the paper's failing ablation)."""
    idx = rng.integers(0, n - 1, size=(n, k))
    return idx + (idx >= np.arange(n)[:, None])


def make_groups(kind: str, topology_groups: np.ndarray, seed: int) -> np.ndarray:
    """(N, k) neighbour indices (-1 = none) for the batching ``kind``."""
    n, k = topology_groups.shape
    if kind == "topology":
        return topology_groups
    if kind == "temporal":
        return temporal_groups(n, k)
    if kind == "random":
        return random_groups(n, k, np.random.default_rng(seed))
    raise ValueError(f"unknown batching {kind!r} (topology, temporal or random)")
