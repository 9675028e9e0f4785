"""Scan sequences: lazy access to N scans (float32 points) with timestamps."""

from __future__ import annotations

import enum
import hashlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from dm2_backend.kernel.trajectory import Trajectory, associate_by_time, interpolate_gaps
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)


@dataclass
class Scan:
    """One scan in the sensor frame: points (M,3) float32, optional per-point fields."""

    points: np.ndarray
    timestamp: float | None = None
    intensity: np.ndarray | None = None
    point_time: np.ndarray | None = None
    ring: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float32).reshape(-1, 3)

    def __len__(self) -> int:
        return len(self.points)


class SensorKind(str, enum.Enum):
    """The kind of sensor a scan sequence comes from (``ScanSequence.sensor``): declared by its scan source
    (``formats.registry.ScanSource.sensor``), or, where the source cannot tell (a folder of scan files, a bag),
    decided once from the scans' geometry (:meth:`of_geometry`, by ``pipeline.inputs``)."""

    LASER_2D = "laser2d"
    LIDAR = "lidar"
    DEPTH_CAMERA = "depth"

    @classmethod
    def of_geometry(cls, planar: bool) -> SensorKind:
        """Scans in one plane come from a 2D laser, others from a LiDAR."""
        return cls.LASER_2D if planar else cls.LIDAR


LASER_2D, LIDAR, DEPTH_CAMERA = SensorKind.LASER_2D, SensorKind.LIDAR, SensorKind.DEPTH_CAMERA


@dataclass
class ScanSequence:
    """N scans loaded on demand by ``loader(i)``.

    ``trajectories`` holds poses the source itself carries (e.g. ``"odometry"`` and ``"logged"`` for
    CARMEN logs, ``"reference"`` for depth sequences), in the sensor frame of the scans.
    """

    loader: Callable[[int], Scan]
    count: int
    timestamps: np.ndarray | None = None
    planar: bool = False
    source: str = ""
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    #: how the scans were read: format, resolved path and every read option (set by ``formats.open_scans``);
    #: with the files it names, it keys the preparation cache, so it must hold everything the reading used
    read_spec: dict = field(default_factory=dict)
    #: the sensor kind: the source's (``formats.open_scans``), else decided from the scans by ``pipeline.inputs``;
    #: None until then
    sensor: SensorKind | None = None

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i: int) -> Scan:
        if not -self.count <= i < self.count:
            raise IndexError(i)
        i %= self.count
        scan = self.loader(i)
        if len(scan) == 0:
            raise InputError(self.source, f"scan {i} is empty")
        if not np.isfinite(scan.points).all():
            scan.points = scan.points[np.isfinite(scan.points).all(axis=1)]
        if scan.timestamp is None and self.timestamps is not None:
            scan.timestamp = float(self.timestamps[i])
        return scan

    def __iter__(self) -> Iterator[Scan]:
        for i in range(self.count):
            yield self[i]

    def subset(self, index: np.ndarray) -> ScanSequence:
        """A lazy view on the scans at the given indices."""
        index = np.asarray(index, dtype=int)
        return ScanSequence(
            loader=lambda i: self.loader(int(index[i])),
            count=len(index),
            timestamps=None if self.timestamps is None else self.timestamps[index],
            planar=self.planar,
            source=self.source,
            trajectories={k: v.subset(index) for k, v in self.trajectories.items() if len(v) == self.count},
            meta=dict(self.meta),
            read_spec={**self.read_spec, "subset": hashlib.sha1(index.tobytes()).hexdigest()[:16]},
            sensor=self.sensor,
        )


def associate_scans(
    scans: ScanSequence, poses: Trajectory, max_diff: float = 0.01, by: str = "auto"
) -> tuple[ScanSequence, Trajectory]:
    """Pair scans with poses by timestamp (when both have them) or by index.

    By index the counts must match; by time every scan must find a pose within ``max_diff`` seconds, or, from a
    trajectory denser than the scans, have one interpolated at its stamp across a short gap (a dropout of a few
    samples: ``trajectory.interpolate_gaps``; logged, and counted in the returned trajectory's
    ``meta["interpolated_gaps"]``).
    """
    timed = scans.timestamps is not None and poses.timestamps is not None
    if by == "time" or (by == "auto" and timed):
        if not timed:
            raise InputError(scans.source, "association by time needs timestamps on scans and poses")
        i_scan, i_pose = associate_by_time(scans.timestamps, poses.timestamps, max_diff)
        if len(i_scan) < len(scans):
            filled = interpolate_gaps(scans.timestamps, poses, i_scan, i_pose)
            if filled is not None:
                log.info("%s", filled.describe())
                return scans, filled.trajectory
            if by == "auto" and len(scans) == len(poses):
                return scans, poses  # stamps in different clocks; the counts agree, pair by index
            raise InputError(
                scans.source,
                f"only {len(i_scan)} of {len(scans)} scans have a pose within {max_diff} s (see --max-diff)",
            )
        return scans.subset(i_scan), poses.subset(i_pose)
    if len(scans) != len(poses):
        raise InputError(scans.source, f"{len(scans)} scans but {len(poses)} poses")
    return scans, poses
