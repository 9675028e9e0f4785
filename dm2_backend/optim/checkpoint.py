"""The optimiser's checkpoint (``checkpoint.pt`` in the run folder): written after every epoch, read by
``dm2 refine --resume`` with ``weights_only=True`` (a file handed to it cannot run code)."""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
import torch

from dm2_backend.optim.epoch import Epoch
from dm2_backend.optim.selection import Best
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError, one_line

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


def load_checkpoint(path: Path, device, frames: int | None = None) -> dict:
    """A checkpoint written by :func:`save_checkpoint`, loaded with ``weights_only=True`` (a file handed to
    ``--resume`` cannot run code), checked: ``frames`` finite rigid motions, a plausible epoch; ``best`` back as
    a :class:`~dm2_backend.optim.selection.Best` and ``history`` as
    :class:`~dm2_backend.optim.epoch.Epoch` records. An unreadable, foreign or damaged file is an
    :class:`InputError` naming it."""
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError) as exc:
        raise InputError(path, f"not a dm2 checkpoint, or a damaged one ({one_line(str(exc))[:200]})") from None
    if not isinstance(state, dict) or not isinstance(state.get("best"), dict) or "poses" not in state["best"]:
        raise InputError(path, "not a dm2 checkpoint (no best poses)")
    poses = state["best"]["poses"]
    try:
        state["best"]["poses"] = poses.cpu().numpy() if isinstance(poses, torch.Tensor) else np.asarray(poses)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"--resume: its best poses are not an array ({one_line(str(exc))[:120]})") from None
    problem = _problem(state, frames)
    if not problem:
        try:
            state["best"] = Best.of_state(state["best"])
            state["history"] = [Epoch.of_row(row) for row in state["history"]]
        except ValueError as exc:
            problem = str(exc)
    if problem:
        raise InputError(path, f"--resume: not a checkpoint of this run ({problem}); run without --resume")
    return state


#: more epochs than any run makes: a checkpoint claiming more is not one of dm2's
MAX_EPOCH = 10**6


def _problem(state: dict, frames: int | None) -> str:
    """What makes ``state`` unfit to continue from, or ""."""
    poses = state["best"]["poses"]
    if poses.dtype.kind != "f" or poses.ndim != 3 or poses.shape[1:] != (4, 4) or \
            (frames is not None and len(poses) != frames):
        return f"best poses of shape {poses.shape}, not ({frames}, 4, 4)"
    if not np.isfinite(poses).all():
        return "its best poses are not finite"
    R = poses[:, :3, :3].astype(np.float64)
    if not np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-4) or not np.allclose(poses[:, 3], [0, 0, 0, 1]) \
            or not np.all(np.linalg.det(R) > 0):
        return "its best poses are not rigid motions"
    epoch = state.get("epoch")
    if not isinstance(epoch, int) or isinstance(epoch, bool) or not 0 <= epoch < MAX_EPOCH:
        return f"epoch {epoch!r}, not 0 to {MAX_EPOCH - 1}"
    if not isinstance(state.get("history"), list):
        return "no epoch history"
    return ""


def save_checkpoint(path: Path, state: dict) -> None:
    """``state`` (see :func:`plain_state`) written atomically."""
    buffer = io.BytesIO()  # serialised first: a full disk is then an OSError of the write, not torch's
    torch.save(state, buffer)
    with atomic_write(path, "wb") as fh:
        fh.write(buffer.getbuffer())
