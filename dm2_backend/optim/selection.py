"""Which poses the optimiser returns (the sharpest map among the start and the epochs, or the epoch of lowest
loss: ``optimiser.select``) and why, in words (``OptimResult.selection``). The best so far is a plain dict (the
checkpoint keeps it): ``loss``, ``epoch`` (-1: the start), ``poses``, and with the map selection ``map`` and
``start_map`` (map entropies)."""

from __future__ import annotations

import math

import numpy as np


def first_candidate(poses: np.ndarray, start_map: float | None) -> dict:
    """The start as the first candidate; ``start_map`` its map entropy when the map selects (else None)."""
    best = {"loss": math.inf, "epoch": -1, "poses": poses}
    if start_map is not None:
        best["map"] = best["start_map"] = start_map
    return best


def offer(best: dict, row: dict, poses: np.ndarray, by_map: bool) -> dict:
    """``best`` after an epoch that agreed with the registrations (``row``: its history row, ``poses``): the
    epoch when its map is sharper (``by_map``) or its loss lower, else ``best`` unchanged."""
    if not (row["map_entropy"] < best["map"] if by_map else row["loss"] < best["loss"]):
        return best
    return {**best, "loss": row["loss"], "epoch": row["epoch"], "poses": poses,
            **({"map": row["map_entropy"]} if by_map else {})}


def selection(best: dict, by_map: bool, rejected: int = 0, epochs: int = 1) -> str:
    """The returned poses (``best``: the epoch, its loss and map entropy, the start's) and why."""
    if epochs == 0:
        return "the start: first-order epochs off (optimiser.first_order)"
    note = f"; {rejected} diverged epochs rejected" if rejected else ""
    return chosen(best, by_map) + note


def chosen(best: dict, by_map: bool) -> str:
    """Why ``best`` was chosen: by the map (``by_map``) or by the loss."""
    if not by_map:
        return f"lowest epoch loss: epoch {best['epoch']}" if best["epoch"] >= 0 else "the start (no epoch ran)"
    if best["epoch"] < 0:
        return f"the start: no epoch made a sharper map (map entropy {best['start_map']:.4f})"
    return f"sharpest map: epoch {best['epoch']} (map entropy {best['map']:.4f}, start {best['start_map']:.4f})"
