"""Place recognition ``poses`` (alias ``gps``): the radius topology computed on a reference trajectory
read from a file (any trajectory format), e.g. ground truth or GPS for ablations."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import assemble, radius_neighbours
from dm2_backend.algorithms.topology import check_k, check_poses, default_radius
from dm2_backend.kernel.prepared import Frames, Topology
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError


@dataclass
class PosesTopology:
    """Options: ``path`` (required) and ``format`` (None: detected) of the reference trajectory."""

    name: ClassVar[str] = "poses"

    path: str | None = None
    format: str | None = None
    #: radius neighbours on the reference trajectory's positions (m); default half the median range
    radius: float | None = None
    #: neighbours per frame: the size of each frame's group (at least 1), nearest first
    k: int = 8
    #: fill each group up to ``k`` with temporal neighbours i-1, i+1, i-2, ...; frame i+1 is always in frame i's
    #: group (every step is registered)
    temporal_fill: bool = True
    #: frames may lie this far (s) outside the reference's time span
    max_time_diff: float = 0.1

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_k(self.k)
        check_poses(frames, poses)
        if not self.path:
            raise InputError(None, f"place recognition {self.name!r} needs option 'path' (a trajectory file)")
        from dm2_backend.formats import read_trajectory

        ref = read_trajectory(Path(self.path), self.format)
        positions = self._positions(frames, ref)
        radius = self.radius or default_radius(frames)
        near = radius_neighbours(positions, radius, self.k)
        topo = assemble([[(j, "radius") for j in row] for row in near], self.k, self.temporal_fill)
        topo.log.append({"plugin": self.name, "path": str(self.path), "radius": radius, "k": self.k})
        return topo

    def _positions(self, frames: Frames, ref: Trajectory) -> np.ndarray:
        """Reference positions at the frames: interpolated in time when both have stamps, else by index."""
        if frames.timestamps is not None and ref.timestamps is not None and len(ref) > 1:
            t, tr = np.asarray(frames.timestamps, float), ref.timestamps
            outside = (t < tr[0] - self.max_time_diff) | (t > tr[-1] + self.max_time_diff)
            if outside.any():
                raise InputError(
                    self.path,
                    f"{int(outside.sum())} frames lie outside the trajectory's time span "
                    f"[{tr[0]:.3f}, {tr[-1]:.3f}] s (first at {t[outside][0]:.3f} s)",
                )
            return np.column_stack([np.interp(t, tr, ref.positions[:, c]) for c in range(3)])
        if len(ref) != len(frames):
            raise InputError(self.path, f"{len(ref)} poses for {len(frames)} frames and no timestamps to match")
        return ref.positions


@dataclass
class GpsTopology(PosesTopology):
    """The ``poses`` topology under the name ``gps`` (positions only are used)."""

    name: ClassVar[str] = "gps"
