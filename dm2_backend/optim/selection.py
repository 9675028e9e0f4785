"""Which poses the optimiser returns, in words (``OptimResult.selection``): the sharpest map among the start and
the epochs, or the epoch of lowest loss (``optimiser.select``)."""

from __future__ import annotations


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
