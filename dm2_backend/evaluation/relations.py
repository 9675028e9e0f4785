"""The Freiburg relations metric (Kuemmerle et al., "On measuring the accuracy of SLAM algorithms", 2009).

Each relation ``t1 t2 x y z roll pitch yaw`` is the pose at t2 expressed in the frame of the pose at t1.
For each relation the estimated poses nearest in time to t1 and t2 (within ``max_dt``, numerical matching
with ``np.searchsorted``) give ``delta = x(t1)^-1 (+) x(t2)`` (SE(2) for planar trajectories, SE(3)
otherwise); the relation is subtracted component-wise (x, y, z, roll, pitch, yaw), angle differences are
wrapped to [-pi, pi); the translational error is the norm of the xyz part, the rotational error the norm
of the angle part. Reported: mean and sample standard deviation (ddof=1) of the absolute errors (m, deg)
and of the squared errors (m^2, deg^2), with the counts used and skipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

#: default time tolerance between a relation's stamp and the nearest estimated pose, seconds
MAX_DT = 0.1


@dataclass
class RelationsResult:
    """Per-relation errors of the relations that matched, and their summary."""

    trans_errors: np.ndarray  # m
    rot_errors_deg: np.ndarray  # deg
    used: int
    skipped: int
    planar: bool
    max_dt: float

    @property
    def count(self) -> int:
        return self.used

    @property
    def stats(self) -> dict[str, float]:
        """``trans_mean trans_std trans_sq_mean trans_sq_std rot_mean rot_std rot_sq_mean rot_sq_std``."""
        out = {}
        for name, e in (("trans", self.trans_errors), ("rot", self.rot_errors_deg)):
            for suffix, v in (("", e), ("_sq", e**2)):
                out[f"{name}{suffix}_mean"] = float(np.mean(v))
                out[f"{name}{suffix}_std"] = float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")
        return out


def load_relations(path: str | Path) -> np.ndarray:
    """Relations (M,8) ``t1 t2 x y z roll pitch yaw`` of a Freiburg ``.relations`` file."""
    from dm2_backend.formats.relations import read_relations

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    return np.asarray(read_relations(path), dtype=np.float64).reshape(-1, 8)


def _nearest(stamps: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest stamp (sorted ``stamps``) for each ``t``, and the absolute time difference."""
    right = np.clip(np.searchsorted(stamps, t), 0, len(stamps) - 1)
    left = np.clip(right - 1, 0, len(stamps) - 1)
    pick = np.where(np.abs(stamps[left] - t) <= np.abs(stamps[right] - t), left, right)
    return pick, np.abs(stamps[pick] - t)


def _components(T: np.ndarray, planar: bool) -> np.ndarray:
    """(N,6) ``x y z roll pitch yaw`` of relative poses."""
    if planar:
        xy_yaw = se3.to_xy_yaw(T)
        zeros = np.zeros(len(T))
        return np.stack([xy_yaw[:, 0], xy_yaw[:, 1], zeros, zeros, zeros, xy_yaw[:, 2]], axis=1)
    return np.concatenate([T[:, :3, 3], se3.matrix_to_rpy(T[:, :3, :3])], axis=1)


def relations_error(
    est: Trajectory,
    relations: np.ndarray,
    *,
    max_dt: float = MAX_DT,
    planar: bool | None = None,
    source: str | Path | None = None,
) -> RelationsResult:
    """Relations metric of ``est`` (needs timestamps); ``planar`` defaults to the trajectory's own flag
    or to whether its poses lie in the plane. Unsorted timestamps (some CARMEN logs) are sorted first."""
    if est.timestamps is None:
        raise InputError(source, "the estimate has no timestamps; the relations metric needs them")
    relations = np.asarray(relations, dtype=np.float64).reshape(-1, 8)
    order = np.argsort(est.timestamps, kind="stable")
    stamps, poses = est.timestamps[order], est.poses[order]
    if planar is None:
        planar = bool(est.planar or se3.is_planar(poses))
    i1, dt1 = _nearest(stamps, relations[:, 0])
    i2, dt2 = _nearest(stamps, relations[:, 1])
    ok = (dt1 <= max_dt) & (dt2 <= max_dt)
    if not ok.any():
        raise InputError(source, f"no relation has estimated poses within {max_dt} s of both its stamps")
    delta = se3.relative(poses[i1[ok]], poses[i2[ok]])
    err = _components(delta, planar) - relations[ok, 2:]
    err[:, 3:] = se3.wrap_angle(err[:, 3:])
    return RelationsResult(
        trans_errors=np.linalg.norm(err[:, :3], axis=1),
        rot_errors_deg=np.degrees(np.linalg.norm(err[:, 3:], axis=1)),
        used=int(ok.sum()),
        skipped=int((~ok).sum()),
        planar=planar,
        max_dt=max_dt,
    )
