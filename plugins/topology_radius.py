"""Place recognition ``radius``: the frames nearest to each warm-start position within a radius, filled
up with temporal neighbours (as the official DeepMapping2 custom-data recipe does)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import assemble, radius_neighbours
from dm2_backend.algorithms.topology import check_k, check_poses, default_radius
from dm2_backend.kernel.prepared import Frames, Topology


@dataclass
class RadiusTopology:
    """Options; ``radius`` None means half the median range of the scans."""

    name: ClassVar[str] = "radius"

    radius: float | None = None
    #: neighbours per frame: the size of each frame's group (at least 1), nearest first
    k: int = 8
    #: fill groups up to k with temporal neighbours i-1, i+1, i-2, ...
    temporal_fill: bool = True

    def run(self, frames: Frames, poses: np.ndarray) -> Topology:
        check_k(self.k)
        check_poses(frames, poses)
        radius = self.radius or default_radius(frames)
        near = radius_neighbours(poses[:, :3, 3], radius, self.k)
        topo = assemble([[(j, "radius") for j in row] for row in near], self.k, self.temporal_fill)
        topo.log.append({"plugin": self.name, "radius": radius, "k": self.k})
        return topo
