"""Warm start ``poses``: the user's trajectory as given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import project_planar
from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError


@dataclass
class PosesWarmStart:
    """Use the given trajectory (one pose per frame)."""

    name: ClassVar[str] = "poses"

    def run(self, frames: Frames, given: Trajectory | None) -> np.ndarray:
        if given is None:
            raise InputError(None, "warm start 'poses' needs a trajectory (give one, or use warm start 'icp')")
        if len(given) != len(frames):
            raise InputError(None, f"warm start 'poses': {len(given)} poses for {len(frames)} frames")
        poses = np.array(given.poses, dtype=np.float64)
        if not np.isfinite(poses).all():
            raise InputError(None, "warm start 'poses': the trajectory has non-finite poses")
        return project_planar(poses) if frames.planar else poses
