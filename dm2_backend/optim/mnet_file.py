"""The trained M-Net of a run as a file: ``mnet.pt``, saved by the optimiser and rebuilt for the maps.

``mnet.pt`` (written by the optimiser at the end of ``dm2 refine``, next to ``checkpoint.pt``) holds only
tensors and plain values, so it loads with ``torch.load(weights_only=True)``: the occupancy field's
``state_dict``, its constructor arguments, and ``world_from_field``, the 4x4 transform from the field's
coordinates to the world of the run's poses (the optimiser re-anchors its poses on the first frame's start
pose; the field lives in the optimiser's own frame). ``trained`` is False when the run did not use the
occupancy loss (``use_bce`` off when polishing a locally accurate 3D start) or ran no epoch (the first-order
epochs are off after the dense stage): the field is then untrained and no M-Net map or mesh is made from it.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dm2_backend.optim.occupancy import GridOccupancy
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

MNET = "mnet.pt"
FORMAT = "dm2-mnet/1"


def save_mnet(path: Path, field: GridOccupancy, world_from_field: np.ndarray, trained: bool = True) -> None:
    state = {
        "format": FORMAT,
        "dim": int(field.dim),
        "args": dict(field.init_args),
        "state_dict": {k: v.detach().cpu().clone() for k, v in field.state_dict().items()},
        "world_from_field": np.asarray(world_from_field, dtype=np.float64).tolist(),
        "trained": bool(trained),
    }
    buffer = io.BytesIO()  # serialised first: a full disk is then an OSError of the write, not torch's
    torch.save(state, buffer)
    with atomic_write(path, "wb") as fh:
        fh.write(buffer.getbuffer())


@dataclass
class MNet:
    """The occupancy field of a run, evaluated at world points."""

    field: GridOccupancy
    world_from_field: np.ndarray
    trained: bool = True

    @property
    def dim(self) -> int:
        return self.field.dim

    @property
    def finest_cell(self) -> float:
        """Edge (m) of the finest feature grid's cells: the field's own resolution."""
        span = self.field.span.cpu().numpy()
        return float(span.max() / max(self.field.resolutions))

    def logits(self, world: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
        """Occupancy logits at world points (N, 2 or 3): ``> 0`` is occupied."""
        world = np.asarray(world, dtype=np.float64)
        if world.shape[-1] == 2:
            world = np.concatenate([world, np.zeros((*world.shape[:-1], 1))], -1)
        inv = np.linalg.inv(self.world_from_field)
        local = world.reshape(-1, 3) @ inv[:3, :3].T + inv[:3, 3]
        out = np.empty(len(local), np.float32)
        with torch.no_grad():
            for s in range(0, len(local), chunk):
                x = torch.from_numpy(local[s : s + chunk, : self.dim].astype(np.float32))
                out[s : s + chunk] = self.field(x).numpy()
        return out.reshape(world.shape[:-1])

    def probability(self, world: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logits(world).astype(np.float64)))


def load_mnet(path: Path) -> MNet:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as exc:
        raise InputError(path, f"cannot read the M-Net: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise InputError(path, f"not a dm2 M-Net file ({FORMAT})")
    field = GridOccupancy(**state["args"])
    field.load_state_dict(state["state_dict"])
    field.eval()
    return MNet(field, np.asarray(state["world_from_field"], dtype=np.float64), bool(state["trained"]))
