"""Warm start ``kiss-icp``: KISS-ICP odometry (Vizzo et al. 2023) over the frames; optional dependency
(``pip install dm2[kiss]``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import lengths, project_planar
from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.progress import progress


@dataclass
class KissWarmStart:
    """Options; None means derived from the data (``Frames.scale``)."""

    name: ClassVar[str] = "kiss-icp"
    #: the optional package this plugin needs and the extra that installs it (``dm2 plugins`` reports it)
    requires: ClassVar[tuple[str, str]] = ("kiss_icp", "dm2[kiss]")

    #: points farther than this are ignored (m); default 1.5x the 90th-percentile range
    max_range: float | None = None
    #: KISS-ICP map voxel (m); default KISS-ICP's own max_range / 100
    voxel_size: float | None = None
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, given: Trajectory | None) -> np.ndarray:
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError:
            raise InputError(None, "warm start 'kiss-icp' needs kiss-icp: install dm2[kiss]") from None
        scale = lengths(frames)
        max_range = self.max_range or 1.5 * scale.range_p90
        config = KISSConfig()
        config.data.max_range, config.data.min_range, config.data.deskew = float(max_range), 0.0, False
        config.mapping.voxel_size = float(self.voxel_size or max_range / 100.0)
        odometry = KissICP(config=config)
        poses = np.tile(np.eye(4), (len(frames), 1, 1))
        empty = np.zeros(0)
        for i, pts in enumerate(progress(frames.points, "kiss-icp", unit="frame", enabled=self.progress)):
            odometry.register_frame(np.asarray(pts, dtype=np.float64), empty)
            poses[i] = odometry.last_pose
        if frames.planar:
            poses = project_planar(poses)
        if given is not None and len(given) == len(frames):
            poses = given.poses[0] @ poses  # start where the given trajectory starts
        return poses
