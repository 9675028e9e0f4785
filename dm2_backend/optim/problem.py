"""What the first-order stage is given: the problem (frames, registrations, start), what rank 0 watches per epoch,
and how the epochs run."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.optim.distributed import Dist


@dataclass(frozen=True)
class Problem:
    """The prepared frames, their topology and registrations, and the poses the epochs start from."""

    frames: Frames
    topology: Topology
    pairwise: Pairwise
    start: np.ndarray
    #: the start agrees with the registrations by construction (the pose-graph solution, the dense stage's result)
    locally_accurate: bool = False
    #: the dense stage ran before: the epochs then run only when ``optimiser.first_order`` asks for them
    after_dense: bool = False


@dataclass(frozen=True)
class Watch:
    """What rank 0 evaluates per epoch: ``metric`` accuracy against ground truth (shown, never used to
    choose), ``map_metric`` the map entropy (chooses the returned poses, see ``OptimConfig.select``), ``trace``
    the accuracy recorded a few times per epoch with the loss (each epoch row's ``trace``)."""

    metric: Callable[[np.ndarray], float] | None = None
    map_metric: Callable[[np.ndarray], float] | None = None
    trace: Callable[[np.ndarray], float] | None = None


@dataclass(frozen=True)
class Execution:
    """How the epochs run: the seed, the device (``auto``: CUDA when present), the progress bar, the points of
    ``trainer.sample_points`` computed ahead (a memory-mapped array the ranks share; None: drawn here) and this
    process's rank when several optimise together (None: one process)."""

    seed: int = 0
    device: str = "auto"
    progress: bool = True
    samples: np.ndarray | None = None
    dist: Dist | None = None
