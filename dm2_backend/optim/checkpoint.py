"""The optimiser's checkpoint (``checkpoint.pt`` in the run folder): written after every epoch, read by
``dm2 refine --resume`` with ``weights_only=True`` (a file handed to it cannot run code)."""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
import torch

from dm2_backend.atomic import atomic_write
from dm2_backend.errors import InputError, one_line

CHECKPOINT = "checkpoint.pt"


def plain_state(value):
    """``value`` with numpy arrays as CPU tensors and numpy scalars / tuples as plain Python values: what
    ``torch.load(weights_only=True)`` accepts."""
    if isinstance(value, dict):
        return {k: plain_state(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain_state(v) for v in value]
    if isinstance(value, tuple):
        return tuple(plain_state(v) for v in value)
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def load_checkpoint(path: Path, device) -> dict:
    """A checkpoint written by :func:`save_checkpoint`, loaded with ``weights_only=True`` (a file handed to
    ``--resume`` cannot run code); ``best["poses"]`` back as a numpy array. An unreadable or foreign file is an
    :class:`InputError` naming it."""
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError) as exc:
        raise InputError(path, f"not a dm2 checkpoint, or a damaged one ({one_line(str(exc))[:200]})") from None
    if not isinstance(state, dict) or not isinstance(state.get("best"), dict) or "poses" not in state["best"]:
        raise InputError(path, "not a dm2 checkpoint (no best poses)")
    poses = state["best"]["poses"]
    state["best"]["poses"] = poses.cpu().numpy() if isinstance(poses, torch.Tensor) else np.asarray(poses)
    return state


def save_checkpoint(path: Path, state: dict) -> None:
    """``state`` (see :func:`plain_state`) written atomically."""
    buffer = io.BytesIO()  # serialised first: a full disk is then an OSError of the write, not torch's
    torch.save(state, buffer)
    with atomic_write(path, "wb") as fh:
        fh.write(buffer.getbuffer())
