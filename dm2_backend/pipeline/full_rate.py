"""The input trajectory at its own rate, corrected: when ``--poses`` is denser than the scans (a 100-200 Hz
LIO/VIO trajectory for 10 Hz scans), each scan pose's correction is interpolated onto every input stamp."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FullRate:
    """The corrected input trajectory and how many of its stamps lie outside the scans' span (those keep the
    nearest scan's correction)."""

    trajectory: Trajectory
    outside: int

    def summary(self) -> dict[str, int]:
        return {"poses": len(self.trajectory), "outside_scans_span": self.outside}


def corrected_full_rate(full: Trajectory, at_scans: Trajectory, refined: np.ndarray) -> FullRate:
    """``full`` corrected by the scans' corrections ``refined @ inv(at_scans)`` (world frame: a correction
    that only re-anchors the map is one rigid motion, applied unchanged to every pose), interpolated on SE(3)
    (rotation by slerp, translation linearly) between the stamps of ``at_scans``, the input poses the scans
    were paired with."""
    if full.timestamps is None or at_scans.timestamps is None:
        raise ValueError("a full-rate correction needs timestamps on the input and at the scans")
    corrections = np.asarray(refined, dtype=np.float64) @ se3.inverse(at_scans.poses)
    stamps, first = np.unique(at_scans.timestamps, return_index=True)
    at_full = se3.interpolate(stamps, corrections[first], full.timestamps)
    outside = int(((full.timestamps < stamps[0]) | (full.timestamps > stamps[-1])).sum())
    return FullRate(full.with_poses(at_full @ full.poses), outside)
