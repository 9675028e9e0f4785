"""The dense stage's checkpoint: its poses after each round, so ``dm2 refine --resume`` continues where an
interrupted run left off instead of starting the stage again (minutes at thousands of frames).

The file is input when it is read back: an ``.npz`` without pickles, bounded in size, every array checked
(shape, finite, rigid poses) and tied to the start it was made from (the start poses are kept in it: a run
continues only from the start it was interrupted in, up to the rounding of a registration on another number
of threads), so a checkpoint of another run or a damaged one is one line naming the file, never a silently
different result.
"""

from __future__ import annotations

import io
import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.optim.dense_round import Round
from dm2_backend.optim.odometry_noise import MeasuredNoise
from dm2_backend.optim.stop import Stop, StopReason
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

DENSE_CHECKPOINT = "checkpoint-dense.npz"
#: per frame two 4x4 poses of float64 plus the file's own overhead; anything larger is not a checkpoint of ours
BYTES_PER_FRAME = 2 * 4 * 4 * 8
FIXED_BYTES = 1 << 20
#: largest difference of a pose entry (m, or rotation-matrix units) between the checkpoint's start and this run's
#: (open3d's threads round a registration differently; measured differences are far below this)
START_TOLERANCE = 1e-6


@dataclass
class DenseState:
    """Where the dense stage stands: the poses after ``rounds_done`` rounds, the damping for the next round,
    the rows of the rounds done, ``stopped`` once the stage ended (None while it runs), and the odometry noise
    weighed since the planes settled (None: not measured yet)."""

    poses: np.ndarray
    rounds_done: int
    damping: float
    history: list[Round]
    stopped: Stop | None = None
    odometry: MeasuredNoise | None = None


def save(path: Path, state: DenseState, start: np.ndarray) -> None:
    """Write ``state`` to ``path`` under a temporary name and rename it."""
    buf = io.BytesIO()
    stopped = None if state.stopped is None else {"reason": state.stopped.reason.value, "detail": state.stopped.detail}
    meta = {"rounds_done": state.rounds_done, "damping": state.damping, "stopped": stopped,
            "history": [r.row() for r in state.history],
            "odometry": state.odometry.summary() if state.odometry else None}
    np.savez(buf, poses=np.asarray(state.poses, dtype=np.float64), start=np.asarray(start, dtype=np.float64),
             meta=np.array(json.dumps(meta, default=float)))
    with atomic_write(path, "wb") as fh:
        fh.write(buf.getvalue())


def load(path: Path, start: np.ndarray, rounds: int) -> DenseState:
    """The state in ``path`` for a run from ``start`` of at most ``rounds`` rounds; :class:`InputError` (one
    line naming the file) when it is not one."""
    poses, made_from, meta = _read(path, len(start))
    try:
        return _checked(poses, made_from, meta, start, rounds)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise InputError(path, f"--resume: this dense-stage checkpoint does not fit this run: {exc}") from None


def check(path: Path, frames: int, rounds: int) -> None:
    """``path`` checked as :func:`load` checks it, before the start poses are known (before the preparation):
    a run of ``frames`` frames and at most ``rounds`` rounds, from whichever start it records."""
    poses, made_from, meta = _read(path, frames)
    try:
        _checked(poses, made_from, meta, made_from, rounds)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise InputError(path, f"--resume: this dense-stage checkpoint does not fit this run: {exc}") from None


def _read(path: Path, frames: int) -> tuple[np.ndarray, np.ndarray, object]:
    """The poses, start poses and record of the checkpoint of ``frames`` frames in ``path``, bounded."""
    limit = FIXED_BYTES + BYTES_PER_FRAME * frames
    try:
        size = path.stat().st_size
        if size > limit:
            raise ValueError(f"{size} bytes, more than a checkpoint of {frames} frames can be ({limit})")
        arrays = _members(path, limit, {"poses": (frames, 4, 4), "start": (frames, 4, 4), "meta": ()})
        poses = np.array(arrays["poses"], dtype=np.float64)
        made_from = np.array(arrays["start"], dtype=np.float64)
        meta = json.loads(str(arrays["meta"]))
    except (OSError, ValueError, KeyError, EOFError, RecursionError, zipfile.BadZipFile, zlib.error,
            NotImplementedError, RuntimeError) as exc:
        raise InputError(path, f"not a dm2 dense-stage checkpoint, or a damaged one ({str(exc)[:160]})") from None
    return poses, made_from, meta


def _members(path: Path, limit: int, shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """The ``.npz`` members ``shapes`` names, each bounded before it is decoded: only those members, each at most
    ``limit`` bytes uncompressed (as its zip entry declares; a reader stops there) and of the named shape (its
    ``.npy`` header read first: a header may claim any size)."""
    out = {}
    with zipfile.ZipFile(path) as archive:
        infos = {info.filename: info for info in archive.infolist()}
        if set(infos) != {f"{name}.npy" for name in shapes}:
            raise ValueError(f"members {sorted(infos)[:5]}, not {sorted(shapes)}")
        for name, shape in shapes.items():
            info = infos[f"{name}.npy"]
            if info.file_size > limit:
                raise ValueError(f"{name} holds {info.file_size} bytes uncompressed, more than {limit}")
            with archive.open(info) as fh:
                data = io.BytesIO(fh.read(limit + 1))
            version = np.lib.format.read_magic(data)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            declared, _, _ = read_header(data)
            if declared != shape:
                raise ValueError(f"{name} of shape {declared}, not {shape}")
            data.seek(0)
            out[name] = np.load(data, allow_pickle=False)
    return out


def _checked(poses: np.ndarray, made_from: np.ndarray, meta: dict, start: np.ndarray, rounds: int) -> DenseState:
    if not isinstance(meta, dict):
        raise ValueError("its record is not a mapping")
    for name, p in (("poses", poses), ("start poses", made_from)):
        if p.shape != np.shape(start) or not np.all(np.isfinite(p)):
            raise ValueError(f"{name} of shape {p.shape}, not {np.shape(start)} finite ones")
    differ = float(np.abs(made_from - start).max(initial=0.0))
    if differ > START_TOLERANCE:
        raise ValueError(f"it was made from other start poses (differing by up to {differ:.3g})")
    R = poses[:, :3, :3]
    if not np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-6) or not np.allclose(
            poses[:, 3], [0, 0, 0, 1]) or not np.all(np.linalg.det(R) > 0):
        raise ValueError("its poses are not rigid motions")
    done, damping, history, stopped = meta["rounds_done"], meta["damping"], meta["history"], meta["stopped"]
    if not isinstance(done, int) or not 0 <= done <= rounds:
        raise ValueError(f"rounds done {done!r}, not 0 to {rounds}")
    if not isinstance(damping, float | int) or not np.isfinite(damping) or damping <= 0:
        raise ValueError(f"damping {damping!r}")
    if not isinstance(history, list) or len(history) > done:
        raise ValueError("its round records do not match its rounds")
    history = [Round.of_row(r, len(start)) for r in history]
    odometry = meta.get("odometry")
    odometry = None if odometry is None else MeasuredNoise.of_summary(odometry, len(start))
    return DenseState(poses, done, float(damping), history, _stop(stopped), odometry)


#: how a checkpoint of an earlier dm2 worded each end (its record was the text alone)
_EARLIER_WORDS = (("converged in round", StopReason.CONVERGED), ("no step lowered", StopReason.NO_DESCENT),
                  ("rounds", StopReason.BUDGET))


def _stop(record: object) -> Stop | None:
    """The end a checkpoint recorded: None (still running) or a known reason with a short text (an earlier dm2's
    text alone: "" while running, else its reason read from its words)."""
    if record is None or record == "":
        return None
    if isinstance(record, str) and len(record) <= 500:
        reason = next((r for words, r in _EARLIER_WORDS if words in record), None)
        if reason is None:
            raise ValueError("its end record is not a known reason with a short text")
        return Stop(reason, record)
    reasons = {r.value: r for r in StopReason}
    if (not isinstance(record, dict) or record.get("reason") not in reasons or not isinstance(record.get("detail"), str)
            or len(record["detail"]) > 500):
        raise ValueError("its end record is not a known reason with a short text")
    return Stop(reasons[record["reason"]], record["detail"])
