"""Trajectory: N poses in SE(3) with optional timestamps and frame ids."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.errors import InputError


@dataclass
class Trajectory:
    """N poses (N,4,4) float64; timestamps in seconds (float64, never rounded) when known.

    ``planar`` marks 2D data (z = 0, yaw only). ``meta`` carries format details a writer may reuse
    (e.g. a bag's frame ids).
    """

    poses: np.ndarray
    timestamps: np.ndarray | None = None
    frame_ids: list[str] | None = None
    planar: bool = False
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if self.timestamps is not None:
            self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
            if len(self.timestamps) != len(self.poses):
                raise ValueError(f"{len(self.timestamps)} timestamps for {len(self.poses)} poses")
        if self.frame_ids is not None and len(self.frame_ids) != len(self.poses):
            raise ValueError(f"{len(self.frame_ids)} frame ids for {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def subset(self, index: np.ndarray | slice) -> Trajectory:
        """The trajectory at the given indices (or slice)."""
        idx = np.arange(len(self))[index]
        return replace(
            self,
            poses=self.poses[idx],
            timestamps=None if self.timestamps is None else self.timestamps[idx],
            frame_ids=None if self.frame_ids is None else [self.frame_ids[i] for i in idx],
        )

    def with_poses(self, poses: np.ndarray) -> Trajectory:
        """Same timestamps and ids, new poses."""
        return replace(self, poses=np.asarray(poses, dtype=np.float64))

    def transformed(self, left: np.ndarray | None = None, right: np.ndarray | None = None) -> Trajectory:
        """``left @ T_i @ right`` for every pose (change of world / body frame)."""
        poses = self.poses
        if left is not None:
            poses = left @ poses
        if right is not None:
            poses = poses @ right
        return self.with_poses(poses)

    def validate(self, source: str | Path | None = None, first_line: int | None = None) -> Trajectory:
        """Check finiteness, rotations and timestamp order; raise :class:`InputError` naming the pose."""
        validate_poses(self.poses, source, first_line)
        if self.timestamps is not None:
            validate_timestamps(self.timestamps, source, first_line)
        return self


#: positions further than this from the origin (metres) are refused: no map is that large, and distances
#: between such numbers overflow
MAX_POSITION = 1e9


def _line(first_line: int | None, i: int) -> int | None:
    return None if first_line is None else first_line + i


def validate_poses(poses: np.ndarray, source: str | Path | None, first_line: int | None = None) -> None:
    """Raise :class:`InputError` for non-finite values or rotations that are not rotations (beyond
    ``se3.ROTATION_TOL``). Rotations off by more than 1e-6 (evo's own SO(3) check) but within the tolerance
    are snapped to SO(3) in place; finer print rounding stays exactly as read."""
    bad = ~np.isfinite(poses).all(axis=(1, 2))
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(source, f"pose {i} has NaN or infinite values", line=_line(first_line, i))
    far = np.abs(poses[:, :3, 3]).max(axis=1, initial=0.0) > MAX_POSITION if len(poses) else np.zeros(0, bool)
    if far.any():
        i = int(np.argmax(far))
        where = np.abs(poses[i, :3, 3]).max()
        raise InputError(source, f"pose {i} has a position {where:.3g} m from the origin (more than "
                                 f"{MAX_POSITION:.0e} m: a broken number)", line=_line(first_line, i))
    err = se3.rotation_error(poses[:, :3, :3])
    if (err > se3.ROTATION_TOL).any():
        i = int(np.argmax(err > se3.ROTATION_TOL))
        raise InputError(
            source, f"pose {i} has a rotation that is not a rotation (error {err[i]:.2g})",
            line=_line(first_line, i),
        )
    off = err > 1e-6
    if off.any():
        poses[off, :3, :3] = se3.project_to_so3(poses[off, :3, :3])


def validate_timestamps(stamps: np.ndarray, source: str | Path | None, first_line: int | None = None,
                        duplicates_ok: bool = False) -> None:
    """Raise :class:`InputError` for non-finite, unsorted or (unless ``duplicates_ok``) duplicate timestamps."""
    if not np.isfinite(stamps).all():
        i = int(np.argmax(~np.isfinite(stamps)))
        raise InputError(source, f"timestamp {i} is not finite", line=_line(first_line, i))
    d = np.diff(stamps)
    bad = d < 0 if duplicates_ok else d <= 0
    if bad.any():
        i = int(np.argmax(bad)) + 1
        kind = "duplicate" if d[i - 1] == 0 else "unsorted"
        now, before = float(stamps[i]), float(stamps[i - 1])
        hint = " (--duplicate-times keep-first keeps the first pose of each)" if kind == "duplicate" else ""
        raise InputError(
            source, f"{kind} timestamp {now!r} after {before!r}{hint}", line=_line(first_line, i)
        )


def associate_by_time(a: np.ndarray, b: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) pairing each stamp of ``a`` with the nearest unused stamp of ``b`` within
    ``max_diff`` seconds, as evo's ``associate_trajectories`` does (sorted inputs)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    pos = np.clip(np.searchsorted(b, a), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(a), int)
    left = np.maximum(pos - 1, 0)
    nearest = np.where(np.abs(b[left] - a) <= np.abs(b[pos] - a), left, pos)
    ok = np.abs(b[nearest] - a) <= max_diff
    ia = np.flatnonzero(ok)
    ib = nearest[ok]
    _, first = np.unique(ib, return_index=True)  # each stamp of b used once
    keep = np.sort(first)
    return ia[keep], ib[keep]


#: a stamp with no pose within --max-diff takes one interpolated from a dense trajectory when that has a pose on
#: each side of it within this many of its own (median) periods, or within one period of the stamps: dropouts of
#: a few samples (motion capture), no longer than the stamps' own spacing, not holes across which the motion is
#: unknown
GAP_PERIODS = 5
#: "dense": at least this many poses per period of the stamps (a trajectory at the stamps' own rate, whose median
#: period differs from theirs only by clock jitter, is not dense and its gaps are not bridged)
DENSE_FACTOR = 2


@dataclass(frozen=True)
class GapFill:
    """One pose per stamp from a dense trajectory: the associated pose where one lies within ``max_diff``, else
    interpolated on SE(3) at the stamp (:func:`interpolate_gaps`)."""

    trajectory: Trajectory
    #: indices of the stamps whose pose was interpolated
    interpolated: np.ndarray
    #: the widest interval between the two poses an interpolated one lies between (s), the trajectory's period (s)
    widest: float
    period: float

    def summary(self) -> dict:
        return {"interpolated": len(self.interpolated), "of": len(self.trajectory), "widest_gap_s": self.widest,
                "period_s": self.period}

    def describe(self, what: str = "scan poses") -> str:
        """``interpolated 2 of 241 scan poses from the trajectory (gaps up to 0.03 s, 3 periods)``."""
        return (f"interpolated {len(self.interpolated)} of {len(self.trajectory)} {what} from the trajectory "
                f"(gaps up to {self.widest:.3g} s, {self.widest / self.period:.3g} periods)")


def interpolate_gaps(stamps: np.ndarray, traj: Trajectory, i_a: np.ndarray, i_b: np.ndarray) -> GapFill | None:
    """Poses at every one of ``stamps`` (sorted) from ``traj`` associated with them as ``i_a``, ``i_b`` by
    :func:`associate_by_time`: the associated pose where there is one (unchanged, with its own stamp), else
    interpolated at the stamp (``se3.interpolate``: slerp and linear) from the poses on either side, when the
    trajectory is dense (:data:`DENSE_FACTOR`) and both lie within :data:`GAP_PERIODS` of its periods or one period
    of the stamps. None when the
    trajectory is not dense or some stamp is not so bracketed."""
    a = np.asarray(stamps, dtype=np.float64)
    b = traj.timestamps
    if b is None or len(b) < 2 or len(a) == 0:
        return None
    period = float(np.median(np.diff(b)))
    a_period = float(np.median(np.diff(a))) if len(a) > 1 else np.inf  # one stamp: any trajectory is denser
    if not 0 < period * DENSE_FACTOR <= a_period:
        return None
    missing = np.setdiff1d(np.arange(len(a)), i_a)
    right = np.searchsorted(b, a[missing], side="left")  # first pose at or after the stamp
    left = right - 1
    if (left < 0).any() or (right >= len(b)).any():
        return None
    limit = max(GAP_PERIODS * period, a_period if np.isfinite(a_period) else 0.0)
    if ((a[missing] - b[left]) > limit).any() or ((b[right] - a[missing]) > limit).any():
        return None
    nearest = np.empty(len(a), dtype=int)
    nearest[i_a] = i_b
    nearest[missing] = np.where(a[missing] - b[left] <= b[right] - a[missing], left, right)
    out = traj.subset(nearest)
    poses, times = out.poses.copy(), out.timestamps.copy()
    for i, lo, hi in zip(missing, left, right, strict=True):
        poses[i] = se3.interpolate(b[[lo, hi]], traj.poses[[lo, hi]], a[i:i + 1])[0]
        times[i] = a[i]
    widest = float((b[right] - b[left]).max()) if len(missing) else 0.0
    fill = GapFill(replace(out, poses=poses, timestamps=times, meta=dict(traj.meta)), missing, widest, period)
    fill.trajectory.meta["interpolated_gaps"] = fill.summary()
    return fill


def associate_by_index(n_a: int, n_b: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair the first min(n_a, n_b) items by index."""
    n = min(n_a, n_b)
    return np.arange(n), np.arange(n)
