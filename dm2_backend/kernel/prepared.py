"""The types the preparation hands on (to its own steps, the optimiser, the baselines and the writers): the data
model beside :mod:`dm2_backend.kernel.scans` and :mod:`dm2_backend.kernel.trajectory`."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from dm2_backend.runtime.errors import InputError


@dataclass(frozen=True)
class ScanScale:
    """Lengths taken from the data (m). Each defaults to None, "not measured" (frames built by hand):
    :func:`dm2_backend.algorithms.common.lengths` completes the missing ones from the points."""

    #: median range of the raw scans' points
    range_median: float | None = None
    #: 90th percentile of that range
    range_p90: float | None = None
    #: median point spacing of the raw scans
    spacing_raw: float | None = None
    #: voxel grid of the down-sampled frames (0: none)
    voxel: float | None = None
    #: median point spacing of the down-sampled frames
    spacing: float | None = None

    @property
    def length(self) -> float:
        """The scene's length unit: the median range, 1 m where not measured."""
        return 1.0 if self.range_median is None else self.range_median

    def to_dict(self) -> dict[str, float]:
        """The measured lengths by name, in field order (the cache's ``meta.json`` and the reports)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> ScanScale:
        """The record of :meth:`to_dict`'s dict (keys missing: not measured)."""
        return cls(**{k: float(v) for k, v in d.items()})


@dataclass(frozen=True, eq=False)
class Frames:
    """Down-sampled scans held in memory for preparation and optimisation.

    ``points[i]`` is (M_i, 3) float32 in the sensor frame of frame i. ``scale`` holds the lengths derived
    from the data (:class:`ScanScale`, from :func:`dm2_backend.kernel.scan_scale.derive_scale`).
    """

    points: list[np.ndarray]
    timestamps: np.ndarray | None
    planar: bool
    scale: ScanScale = field(default_factory=ScanScale)
    #: the cache entry the points are memory-mapped from (:data:`POINTS_FILE`, :data:`OFFSETS_FILE`), if any;
    #: frames with other points (``dataclasses.replace``) must drop it
    stored: Path | None = None

    def __len__(self) -> int:
        return len(self.points)

    @property
    def max_points(self) -> int:
        return max((len(p) for p in self.points), default=0)

    def part(self, index: np.ndarray) -> FramesPart:
        """What a task on another process needs of the frames ``index``: where they are stored (read there,
        memory-mapped), else their points."""
        index = np.unique(np.asarray(index, dtype=np.int64))
        carried = () if self.stored is not None else tuple(self.points[i] for i in index)
        return FramesPart(len(self), self.planar, self.scale, index, self.stored, carried)


#: a frames cache entry: every frame's points concatenated (float32 rows), and where each frame starts (N + 1)
POINTS_FILE, OFFSETS_FILE = "points.npy", "offsets.npy"


@dataclass(frozen=True, eq=False)
class FramesPart:
    """Some of a sequence's frames, as a task on another process receives them (:meth:`Frames.part`)."""

    count: int
    planar: bool
    scale: ScanScale
    index: np.ndarray
    stored: Path | None
    carried: tuple[np.ndarray, ...] = ()

    def frames(self) -> Frames:
        """Frames of the whole sequence's length holding these frames' points (the others empty)."""
        points = [np.zeros((0, 3), np.float32)] * self.count
        if self.stored is not None:
            try:
                every = np.load(self.stored / POINTS_FILE, mmap_mode="r", allow_pickle=False)
                offsets = np.load(self.stored / OFFSETS_FILE, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise InputError(self.stored, "a worker cannot read the cached frames there; put --cache-dir on "
                                              f"storage every worker mounts at the same path ({exc})") from None
            if len(offsets) != self.count + 1:
                raise InputError(self.stored, f"holds {len(offsets) - 1} frames, not {self.count}")
            for i in self.index:
                points[i] = np.asarray(every[offsets[i] : offsets[i + 1]])
        else:
            for i, p in zip(self.index, self.carried, strict=True):
                points[i] = p
        return Frames(points, None, self.planar, self.scale, self.stored)


@dataclass(frozen=True)
class Topology:
    """Map topology as groups: ``groups[i]`` = neighbour indices of anchor i (-1 pads), best first."""

    groups: np.ndarray  # (N, k) int
    #: every accepted edge (i, j) with i < j, and where it came from ("temporal", "radius", "loop", ...)
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    edge_kind: list[str] = field(default_factory=list)
    log: list[dict] = field(default_factory=list)
    #: loop-closed poses (N,4,4) when the place recognition corrected the warm start; registration starts
    #: from their relative poses, and the optimiser and baselines from them
    poses: np.ndarray | None = None
    #: ``poses`` closed at least one loop (not only repaired the start): the optimiser then treats them as
    #: accurate; set by the place recognition that made them
    loop_closed: bool = False
    #: loop closures the place recognition kept (0 for one that closes no loops)
    closures: int = 0
    #: warm-start steps (frame k to k + 1) the place recognition repaired before closing loops
    repaired_steps: tuple[int, ...] = ()

    @property
    def k(self) -> int:
        return self.groups.shape[1]


@dataclass(frozen=True, eq=False)
class Pairwise:
    """Pairwise registrations for a topology: ``relative[i, n]`` is T_j^i (frame j = groups[i, n] expressed
    in frame i), ``valid[i, n]`` False where registration failed its gate (see ``reason``)."""

    relative: np.ndarray  # (N, k, 4, 4)
    valid: np.ndarray  # (N, k) bool
    fitness: np.ndarray  # (N, k) overlap fraction
    rmse: np.ndarray  # (N, k) inlier rmse (m)
    reason: dict[tuple[int, int], str] = field(default_factory=dict)
    #: (N, k, 6, 6) float32 (planar scans: (N, k, 3, 3) on [x y yaw]): the registration's point-to-plane
    #: (point-to-line) information for unit residual variance (``Match.hessian``) on T_max^min of the pair
    #: (min(i, j), max(i, j)) that was registered, g2o order; zero where a pair has none (``small-gicp`` gives
    #: none); None when not recorded (3D scans with ``information: isotropic``, the default; planar scans always
    #: record it)
    hessian: np.ndarray | None = None
    #: (N, k) the rms of those point-to-plane residuals (m; ``Match.plane_rmse``), with ``hessian``
    plane_rmse: np.ndarray | None = None
