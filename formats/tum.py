"""TUM RGB-D trajectories: ``timestamp tx ty tz qx qy qz qw`` a line, ``#`` comments, any whitespace.

Timestamps are seconds and are kept and written as float64 without rounding (shortest exact text).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write


def read_tum(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Read a TUM trajectory file (see ``ReadOptions.duplicate_times``)."""
    path = Path(path)
    options = options or ReadOptions()
    rows, lines = _text.read_table(path, (8,), "timestamp tx ty tz qx qy qz qw")
    meta: dict = {}
    stamps = rows[:, 0]
    stamps, rows, lines, repeats_ok = _text.duplicate_times(path, stamps, rows, lines, options, meta)
    _text.check_quaternions(path, rows[:, 4:8], lines)
    poses = se3.from_xyz_quat(rows[:, 1:4], rows[:, 4:8], "xyzw")
    traj = Trajectory(poses=poses, timestamps=stamps, meta=meta)
    return _text.validate(traj, path, lines, repeats_ok)


def write_tum(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> None:
    """Write ``traj`` as TUM; a trajectory without timestamps gets its pose index as the time."""
    path = Path(path)
    stamps = traj.timestamps if traj.timestamps is not None else np.arange(len(traj), dtype=np.float64)
    xyz, q = se3.to_xyz_quat(traj.poses, "xyzw")
    with atomic_write(path) as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, p, r in zip(stamps, xyz, q, strict=True):
            fh.write(f"{_text.fmt(t)} {_text.fmt_row(p)} {_text.fmt_row(r)}\n")


def sniff(path: Path) -> bool:
    """8 numeric columns whose last four are unit quaternions."""
    return _text.sniff_poses(path, 8, 4)


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="tum",
        description="TUM RGB-D text: timestamp tx ty tz qx qy qz qw",
        read=read_tum,
        write=write_tum,
        suffixes=(".txt", ".tum"),
        sniff=sniff,
        repeated_stamps=True,  # read_tum keeps repeated stamps by default, as evo does
    )
)
