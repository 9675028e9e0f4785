"""The three plugin interfaces. A plugin is a dataclass whose fields are its options (from the YAML config
section of the same name) with a ``run`` method; it is registered under an entry-point group of
:mod:`dm2_backend.plugins.registry`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.kernel.trajectory import Trajectory


class WarmStart(Protocol):
    """Initial global poses (N,4,4) for the frames; ``given`` is the user's trajectory if any."""

    def run(self, frames: Frames, given: Trajectory | None) -> np.ndarray: ...


class PlaceRecognition(Protocol):
    """Map topology on the warm-start poses."""

    def run(self, frames: Frames, poses: np.ndarray) -> Topology: ...


class Registration(Protocol):
    """Pairwise registrations T_j^i for every (anchor i, neighbour j) of the topology, initialised from the
    warm-start relative pose inv(T_i) @ T_j."""

    def run(self, frames: Frames, poses: np.ndarray, topology: Topology) -> Pairwise: ...
