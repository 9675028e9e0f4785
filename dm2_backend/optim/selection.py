"""Which poses the optimiser returns (the sharpest map among the start and the epochs, or the epoch of lowest
loss: ``optimiser.select``) and why, in words (``OptimResult.selection``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dm2_backend.optim.epoch import Epoch


@dataclass(frozen=True, eq=False)
class Best:
    """The candidate returned so far: its ``poses``, the ``epoch`` that made them (-1: the start) and its mean
    loss; with the map selection its map entropy (``map``) and the start's (``start_map``)."""

    poses: np.ndarray
    epoch: int = -1
    loss: float = math.inf
    map: float | None = None
    start_map: float | None = None

    def state(self) -> dict:
        """The checkpoint's record of it (plain values and the poses)."""
        return {"poses": self.poses, "epoch": self.epoch, "loss": self.loss, "map": self.map,
                "start_map": self.start_map}

    @classmethod
    def of_state(cls, state: dict) -> Best:
        """A checkpoint's record (its poses already checked), every other value checked for its kind
        (ValueError)."""
        epoch, loss = state.get("epoch"), state.get("loss")
        if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < -1:
            raise ValueError("its best epoch is not an epoch")
        if isinstance(loss, bool) or not isinstance(loss, int | float) or math.isnan(loss):
            raise ValueError("its best loss is not a number")
        maps = [state.get(k) for k in ("map", "start_map")]
        if any(m is not None and (isinstance(m, bool) or not isinstance(m, int | float) or math.isnan(m))
               for m in maps):
            raise ValueError("its best map entropy is not a number")
        return cls(state["poses"], epoch, float(loss), *maps)


def first_candidate(poses: np.ndarray, start_map: float | None) -> Best:
    """The start as the first candidate; ``start_map`` its map entropy when the map selects (else None)."""
    return Best(poses, map=start_map, start_map=start_map)


def offer(best: Best, epoch: Epoch, poses: np.ndarray, by_map: bool) -> Best:
    """``best`` after an epoch that agreed with the registrations (``epoch``: its record, ``poses``): the
    epoch when its map is sharper (``by_map``) or its loss lower, else ``best`` unchanged."""
    if not (epoch.map_entropy < best.map if by_map else epoch.loss < best.loss):
        return best
    return replace(best, poses=poses, epoch=epoch.epoch, loss=epoch.loss,
                   map=epoch.map_entropy if by_map else best.map)


def selection(best: Best, by_map: bool, rejected: int = 0, epochs: int = 1) -> str:
    """The returned poses (``best``: the epoch, its loss and map entropy, the start's) and why."""
    if epochs == 0:
        return "the start: first-order epochs off (optimiser.first_order)"
    note = f"; {rejected} diverged epochs rejected" if rejected else ""
    return chosen(best, by_map) + note


def chosen(best: Best, by_map: bool) -> str:
    """Why ``best`` was chosen: by the map (``by_map``) or by the loss."""
    if not by_map:
        return f"lowest epoch loss: epoch {best.epoch}" if best.epoch >= 0 else "the start (no epoch ran)"
    if best.epoch < 0:
        return f"the start: no epoch made a sharper map (map entropy {best.start_map:.4f})"
    return f"sharpest map: epoch {best.epoch} (map entropy {best.map:.4f}, start {best.start_map:.4f})"
