"""KITTI odometry poses: 12 numbers a line, the row-major top 3x4 of each 4x4 pose.

KITTI poses are camera (cam0) poses. With ``ReadOptions.calib`` (a ``calib.txt`` holding a ``Tr:`` line,
velodyne -> camera) the reader converts them to LiDAR poses, ``T_lidar = Tr^-1 @ T_cam @ Tr``, and the writer
converts back. Timestamps come from ``ReadOptions.times`` (``times.txt``, one number a line) or, when it
exists and has one time per pose, from ``times.txt`` next to the poses file.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

CALIB_KEYS = ("Tr:", "Tr_velo_to_cam:", "Tr_velo_cam:")


def _to_poses(rows: np.ndarray) -> np.ndarray:
    poses = se3.identity(len(rows))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def read_calib_tr(path: str | Path) -> np.ndarray:
    """The velodyne -> camera transform ``Tr`` (4,4) of a KITTI ``calib.txt``, its rotation projected onto
    SO(3) (the printed one is off by ~1e-7) so that conversions are exactly invertible."""
    path = Path(path)
    for number, text in enumerate(_text.open_text(path), start=1):
        fields = text.split()
        if fields and fields[0] in CALIB_KEYS:
            if len(fields) != 13:
                raise InputError(path, f"{fields[0]} has {len(fields) - 1} numbers, expected 12", line=number)
            T = _to_poses(np.asarray(_text.parse_floats(path, number, fields[1:])).reshape(1, 12))[0]
            err = float(se3.rotation_error(T[:3, :3]))
            if err > se3.ROTATION_TOL:
                problem = f"{fields[0]} rotation is not a rotation (error {err:.2g})"
                raise InputError(path, problem, line=number)
            T[:3, :3] = se3.project_to_so3(T[:3, :3])  # remove print rounding: an exact rigid transform
            return T
    raise InputError(path, "no 'Tr:' line (velodyne -> camera transform)")


def camera_to_lidar(poses: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """Camera-frame poses (N,4,4) to LiDAR-frame poses: ``Tr^-1 @ T @ Tr``."""
    return se3.inverse(Tr) @ np.asarray(poses, dtype=np.float64) @ Tr


def lidar_to_camera(poses: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """Inverse of :func:`camera_to_lidar`: ``Tr @ T @ Tr^-1``."""
    return Tr @ np.asarray(poses, dtype=np.float64) @ se3.inverse(Tr)


def read_times(path: str | Path, count: int | None = None, duplicates_ok: bool = False) -> np.ndarray:
    """One time (s) a line; checks the count against ``count`` and that times increase (with
    ``duplicates_ok``: do not decrease)."""
    path = Path(path)
    rows, lines = _text.read_table(path, (1,), "one time per line")
    stamps = rows[:, 0]
    if count is not None and len(stamps) != count:
        raise InputError(path, f"{len(stamps)} times for {count} poses")
    traj = Trajectory(poses=se3.identity(len(stamps)), timestamps=stamps)
    _text.validate(traj, path, lines, duplicates_ok)
    return stamps


def times_for(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """``traj`` with the stamps of the times file ``path`` (one a line, one per pose). A repeated stamp (what
    ``--out-times`` writes for a trajectory that has one) is handled as ``options.duplicate_times`` says, as
    the TUM reader does: every pose kept with one warning, the later poses of a run dropped, or refused."""
    path = Path(path)
    rows, lines = _text.read_table(path, (1,), "one time per line")
    if len(rows) != len(traj):
        raise InputError(path, f"{len(rows)} times for {len(traj)} poses")
    meta = dict(traj.meta)
    stamps, kept, lines, repeats_ok = _text.duplicate_times(path, rows[:, 0], np.arange(len(rows)), lines,
                                                            options or ReadOptions(), meta)
    _text.validate(Trajectory(poses=se3.identity(len(stamps)), timestamps=stamps), path, lines, repeats_ok)
    return replace(traj.subset(kept), timestamps=stamps, meta={**meta, "times": str(path)})


def _sibling_times(path: Path, count: int) -> Path | None:
    times = path.with_name("times.txt")
    if times == path or not times.is_file():
        return None
    try:
        read_times(times, count, duplicates_ok=True)  # repeats: as the read options say (times_for)
    except InputError:
        return None
    return times


def read_kitti(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Read KITTI poses; see the module docstring for ``times`` and ``calib``."""
    path = Path(path)
    options = options or ReadOptions()
    rows, lines = _text.read_table(path, (12,), "KITTI pose: 12 numbers, row-major 3x4")
    traj = _text.validate(Trajectory(poses=_to_poses(rows)), path, lines)
    times = Path(options.times) if options.times else _sibling_times(path, len(traj))
    if times is not None:
        traj = times_for(traj, times, options)
    if options.calib:
        traj = traj.with_poses(camera_to_lidar(traj.poses, read_calib_tr(options.calib)))
        traj.meta["frame"] = "lidar"
        traj.meta["calib"] = str(options.calib)
    return traj


def find_calib(*places: Path | None) -> Path | None:
    """The first ``calib.txt`` with a ``Tr`` line beside or in ``places`` (the poses file, the scan folder, its
    parent: KITTI's ``sequences/00/calib.txt`` beside ``sequences/00/velodyne/``)."""
    for place in places:
        if place is None:
            continue
        place = Path(place)
        for folder in ([place, place.parent] if place.is_dir() else [place.parent]):
            candidate = folder / "calib.txt"
            if candidate.is_file():
                try:
                    read_calib_tr(candidate)
                except InputError:
                    continue
                return candidate
    return None


def looks_camera_frame(poses: np.ndarray) -> bool:
    """Whether poses of a ground vehicle look like KITTI camera-frame poses (y down, z forward): the path
    spreads most along z or least along y. LiDAR-frame poses spread along x and y and least along z."""
    xyz = np.asarray(poses)[:, :3, 3]
    if len(xyz) < 3:
        return False
    spread = xyz.std(axis=0)
    if spread.max() <= 0:
        return False
    order = np.argsort(spread)
    clear = spread[order[0]] < 0.3 * spread[order[1]]
    return bool(order[-1] == 2 or (clear and order[0] == 1))


def write_kitti(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> None:
    """Write KITTI poses (exact float text); times to ``options.times`` when given and known."""
    path = Path(path)
    options = options or ReadOptions()
    poses = traj.poses
    if options.calib:
        poses = lidar_to_camera(poses, read_calib_tr(options.calib))
    with atomic_write(path) as fh:
        for T in poses:
            fh.write(_text.fmt_row(T[:3, :].reshape(12)) + "\n")
    if options.times and traj.timestamps is not None:
        with atomic_write(options.times) as fh:
            fh.writelines(_text.fmt(t) + "\n" for t in traj.timestamps)


def sniff(path: Path) -> bool:
    """12 numeric columns holding rotations."""
    rows = _text.sniff_rows(path, 12)
    return rows is not None and bool(np.all(se3.rotation_error(_to_poses(rows)[:, :3, :3]) < 1e-2))


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="kitti",
        description="KITTI odometry poses: 12 numbers a line (row-major 3x4); KITTI's own are camera frame "
                    "(--calib converts them)",
        read=read_kitti,
        write=write_kitti,
        suffixes=(".txt", ".kitti"),
        sniff=sniff,
        stamped=False,  # times.txt beside (written with ``options.times``)
        repeated_stamps=True,  # written as the trajectory has them, read as ``duplicate_times`` says (times_for)
    )
)
