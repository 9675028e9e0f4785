"""BALM (hku-mars/BALM 2.0) pose files: a row-major 4x4 matrix per scan.

BALM's real-world benchmark reads ``alidarPose.csv`` (``read_pose`` in ``benchmark_realworld.cpp``): four lines of
four comma-separated numbers per scan, rows 1-3 the pose ``[R | t]`` (scan to world) and the scan's time in the
last number (row 4 ``0,0,0,time``; BALM reads the time there and ignores the row's other numbers); its scans lie
beside it as ``full<i>.pcd``, numbered from 0 (``dm2 refine --scans <folder> --poses <folder>/alidarPose.csv``
reads them, the folder's scans in natural order). dm2 also reads a plain 4x4 pose file: four lines a pose or all
16 numbers on one line, commas or whitespace; when every last row is ``0 0 0 1`` there are no times. It writes
BALM's form at full precision (shortest exact text), a trajectory without stamps with its pose index as the time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

WHAT = "BALM pose: a row-major 4x4 matrix, four lines of 4 numbers (the time last) or 16 numbers a line"
HOMOGENEOUS = np.array([0.0, 0.0, 0.0, 1.0])


def _matrices(path: Path, rows: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 4, 4) matrices of a table of 4 or 16 columns and the line each starts on."""
    if rows.shape[1] == 16:
        return rows.reshape(-1, 4, 4), lines
    if len(rows) % 4:
        raise InputError(path, f"{len(rows)} rows of 4 numbers are not whole 4x4 matrices (four rows a pose): the "
                               f"last one has {len(rows) % 4}", line=int(lines[-(len(rows) % 4)]))
    return rows.reshape(-1, 4, 4), lines[::4]


def read_balm(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Read a BALM / 4x4 pose file (see the module docstring): stamps from the last element of each matrix,
    none when every last row is ``0 0 0 1``."""
    path = Path(path)
    rows, lines = _text.read_table(path, (4, 16), WHAT)
    mats, starts = _matrices(path, rows, lines)
    poses = se3.identity(len(mats))
    poses[:, :3, :] = mats[:, :3, :]
    last = mats[:, 3, :]
    stamps = None if (last == HOMOGENEOUS).all() else last[:, 3].copy()
    return _text.validate(Trajectory(poses=poses, timestamps=stamps), path, starts)


def write_balm(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> None:
    """Write BALM's ``alidarPose.csv`` form: per pose the rows of ``[R | t]`` and ``0,0,0,time``, comma-separated;
    a trajectory without stamps gets its pose index as the time."""
    stamps = traj.timestamps if traj.timestamps is not None else np.arange(len(traj), dtype=np.float64)
    with atomic_write(Path(path)) as fh:
        for T, t in zip(traj.poses, stamps, strict=True):
            rows = [*np.asarray(T[:3], dtype=np.float64), np.array([0.0, 0.0, 0.0, t])]
            fh.writelines(",".join(map(repr, row.tolist())) + "\n" for row in rows)


def sniff(path: Path) -> bool:
    """Rows of 4 numbers whose groups of four start with rotations, or rows of 16 that are 4x4 poses."""
    for width in (4, 16):
        rows = _text.sniff_rows(path, width)
        if rows is None:
            continue
        whole = len(rows) - len(rows) % 4 if width == 4 else len(rows)
        if whole == 0:
            return False
        mats = rows[:whole].reshape(-1, 4, 4)
        return bool(np.all(se3.rotation_error(mats[:, :3, :3]) < 1e-2))
    return False


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="balm",
        description="BALM alidarPose.csv: a row-major 4x4 pose per scan over four comma-separated lines, the "
                    "time last (also 16 numbers a line; last rows 0 0 0 1: no times)",
        read=read_balm,
        write=write_balm,
        suffixes=(".csv",),
        sniff=sniff,
    )
)
