"""Checks and defaults shared by the place-recognition plugins."""

from __future__ import annotations

import numpy as np

from dm2_backend.algorithms.common import lengths
from dm2_backend.kernel.prepared import Frames
from dm2_backend.runtime.errors import InputError


def default_radius(frames: Frames) -> float:
    """Half the median range: frames this close share most of their view."""
    return 0.5 * lengths(frames).range_median


def check_k(k: int) -> None:
    if k < 1:
        raise InputError(None, f"place recognition: k must be at least 1, got {k}")


def check_poses(frames: Frames, poses: np.ndarray) -> None:
    if poses.shape != (len(frames), 4, 4):
        raise InputError(None, f"place recognition: {poses.shape[0]} poses for {len(frames)} frames")
