"""KITTI raw drives (the ``_sync`` download): Velodyne scans and OXTS GPS/INS poses in the LiDAR frame.

Layout, as published::

    2011_09_26/                          date folder: calib_imu_to_velo.txt (calib_velo_to_cam.txt, ...)
      2011_09_26_drive_0018_sync/        the drive folder: give this path (or its oxts/ or velodyne_points/)
        oxts/data/0000000000.txt ...     one OXTS packet a file: 30 numbers (lat lon alt roll pitch yaw ...)
        oxts/timestamps.txt              'YYYY-MM-DD HH:MM:SS.nnnnnnnnn' a line
        velodyne_points/data/*.bin       float32 x y z reflectance per point
        velodyne_points/timestamps.txt

Poses follow the KITTI devkit (``convert_oxts_to_pose.m``, ``pykitti.utils.load_oxts_packets_and_poses``): a
Mercator projection scaled by the cosine of the first latitude, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the
first position as the origin. They are then expressed in the LiDAR frame, ``T_w_velo = T_w_imu @
inv(T_velo_imu)`` with ``T_velo_imu`` from ``calib_imu_to_velo.txt`` (drive folder first, then the date
folder), and re-based so that the first LiDAR pose is the identity (the KITTI odometry convention).
Trajectory times are the Velodyne stamps of the synced frames (the OXTS stamps are in
``meta["oxts_timestamps"]``); stamps are the clock time read as UTC (KITTI gives no time zone).
"""

from __future__ import annotations

import calendar
import re
from pathlib import Path

import numpy as np

from dm2_backend.formats import _text
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.formats.scan_folder import read_bin, scan_files
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import ScanSequence, SensorKind
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

EARTH_RADIUS = 6378137.0  # m, as in the devkit
OXTS_FIELDS = 30
IMU_TO_VELO = "calib_imu_to_velo.txt"
_STAMP = re.compile(r"(\d{4})-(\d{2})-(\d{2})[ T](\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?")


def drive_root(path: str | Path) -> Path | None:
    """The drive folder of ``path`` (the drive itself, or its ``oxts/`` / ``velodyne_points/``), else None."""
    path = Path(path)
    if path.name in ("oxts", "velodyne_points"):
        path = path.parent
    if path.is_dir() and ((path / "oxts").is_dir() or (path / "velodyne_points").is_dir()):
        return path
    return None


def _root(path: Path) -> Path:
    root = drive_root(path)
    if root is None:
        raise InputError(path, "not a KITTI raw drive folder (expected oxts/ and velodyne_points/ inside)")
    return root


def parse_stamp(text: str) -> float | None:
    """Seconds since the epoch of ``'YYYY-MM-DD HH:MM:SS[.fraction]'`` read as UTC; None when malformed."""
    match = _STAMP.fullmatch(text.strip())
    if match is None:
        return None
    year, month, day, hour, minute, second = (int(g) for g in match.groups()[:6])
    if not (1 <= month <= 12 and 1 <= day <= calendar.monthrange(year, month)[1]
            and hour < 24 and minute < 60 and second < 60):
        return None
    whole = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
    fraction = match.group(7) or "0"
    return whole + int(fraction) / 10 ** len(fraction)


def read_timestamps(path: Path) -> np.ndarray:
    """A ``timestamps.txt`` (blank lines skipped); :class:`InputError` naming the line when malformed."""
    stamps, lines = [], []
    for number, text in enumerate(_text.open_text(path), start=1):
        if not text.strip():
            continue
        value = parse_stamp(text)
        if value is None:
            raise InputError(path, f"expected 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn', got {text.strip()[:40]!r}",
                             line=number)
        stamps.append(value)
        lines.append(number)
    if not stamps:
        raise InputError(path, "no timestamps (empty file?)")
    stamps_arr = np.asarray(stamps, dtype=np.float64)
    _text.validate(Trajectory(poses=se3.identity(len(stamps)), timestamps=stamps_arr), path, np.asarray(lines))
    return stamps_arr


def read_oxts_file(path: Path) -> np.ndarray:
    """The 30 numbers of one OXTS packet file (one line)."""
    rows = list(_text.data_lines(_text.open_text(path)))
    if len(rows) != 1:
        raise InputError(path, f"{len(rows)} data lines, expected one OXTS packet")
    number, fields = rows[0]
    if len(fields) != OXTS_FIELDS:
        raise InputError(path, _text.count_problem(len(fields), (OXTS_FIELDS,), "OXTS packet"), line=number)
    return np.asarray(_text.parse_floats(path, number, fields))


def oxts_poses(packets: np.ndarray) -> np.ndarray:
    """``T_w_imu`` (N,4,4) of OXTS packets (N,30+) exactly as ``pykitti.utils.load_oxts_packets_and_poses``."""
    packets = np.asarray(packets, dtype=np.float64).reshape(len(packets), -1)
    lat, lon, alt = packets[:, 0], packets[:, 1], packets[:, 2]
    scale = np.cos(lat[0] * np.pi / 180.0)
    tx = scale * lon * np.pi * EARTH_RADIUS / 180.0
    ty = scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0))
    t = np.stack([tx, ty, alt], axis=1)
    return se3.make_poses(se3.rpy_to_matrix(packets[:, 3:6]), t - t[0])


def read_calib_rigid(path: Path) -> np.ndarray:
    """A KITTI rigid calibration file (``R:`` 9 numbers row-major, ``T:`` 3 numbers) as a 4x4 transform,
    the printed rotation projected onto SO(3)."""
    values: dict[str, tuple[int, list[float]]] = {}
    for number, text in enumerate(_text.open_text(path), start=1):
        key, _, rest = text.partition(":")
        if key.strip() in ("R", "T"):
            values[key.strip()] = (number, _text.parse_floats(path, number, rest.split()))
    for key, count in (("R", 9), ("T", 3)):
        if key not in values:
            raise InputError(path, f"no '{key}:' line")
        if len(values[key][1]) != count:
            raise InputError(path, f"{key}: has {len(values[key][1])} numbers, expected {count}", line=values[key][0])
    R = np.asarray(values["R"][1]).reshape(3, 3)
    err = float(se3.rotation_error(R))
    if err > se3.ROTATION_TOL:
        raise InputError(path, f"R: is not a rotation (error {err:.2g})", line=values["R"][0])
    return se3.make_poses(se3.project_to_so3(R), np.asarray(values["T"][1]))


def find_calib(root: Path, name: str = IMU_TO_VELO) -> Path:
    """``name`` in the drive folder or its date folder; :class:`InputError` naming both places."""
    for folder in (root, root.parent):
        if (folder / name).is_file():
            return folder / name
    raise InputError(root.parent / name, f"missing calibration file (looked in {root} and {root.parent})")


def _data_files(root: Path, sensor: str, suffix: str) -> list[Path]:
    folder = root / sensor / "data"
    if not folder.is_dir():
        raise InputError(folder, "no such folder")
    files = sorted(folder.glob(f"*{suffix}"))
    if not files:
        hint = " (the unsynced 'extract' download stores text; use the _sync one)" if sensor != "oxts" else ""
        raise InputError(folder, f"no {suffix} files{hint}")
    return files


def _stamps_for(root: Path, sensor: str, count: int) -> np.ndarray:
    path = root / sensor / "timestamps.txt"
    stamps = read_timestamps(path)
    if len(stamps) != count:
        raise InputError(path, f"{len(stamps)} timestamps for {count} files in {sensor}/data")
    return stamps


def read_drive(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """OXTS poses of a drive in the LiDAR frame, first pose identity (see the module docstring)."""
    root = _root(Path(path))
    oxts_files = _data_files(root, "oxts", ".txt")
    oxts_stamps = _stamps_for(root, "oxts", len(oxts_files))
    packets = np.stack([read_oxts_file(f) for f in oxts_files])
    calib = find_calib(root)
    T_velo_imu = read_calib_rigid(calib)
    T_w_velo = oxts_poses(packets) @ se3.inverse(T_velo_imu)
    poses = se3.inverse(T_w_velo[0]) @ T_w_velo
    stamps = oxts_stamps
    if (root / "velodyne_points").is_dir():
        scans = _data_files(root, "velodyne_points", ".bin")
        if len(scans) != len(oxts_files):
            raise InputError(root, f"{len(oxts_files)} OXTS packets but {len(scans)} Velodyne scans")
        stamps = _stamps_for(root, "velodyne_points", len(scans))
    meta = {"frame": "lidar", "calib": str(calib), "oxts_timestamps": oxts_stamps,
            "origin_lat_lon_alt": tuple(float(v) for v in packets[0, :3])}
    traj = Trajectory(poses=poses, timestamps=stamps, meta=meta)
    return traj.validate(root / "oxts" / "data")


def open_drive(path: Path, options: ReadOptions) -> ScanSequence:
    """The Velodyne scans of a drive, stamped from ``velodyne_points/timestamps.txt``."""
    root = _root(path)
    _data_files(root, "velodyne_points", ".bin")
    files = scan_files(root / "velodyne_points" / "data")
    stamps = _stamps_for(root, "velodyne_points", len(files))
    return ScanSequence(loader=lambda i: read_bin(files[i]), count=len(files), timestamps=stamps,
                        source=str(root), meta={"files": files, "times_from": "velodyne_points/timestamps.txt"})


def _sniff(sensor: str):
    def sniff(path: Path) -> bool:
        root = drive_root(path)
        return root is not None and (root / sensor / "data").is_dir()

    return sniff


def describe(path: Path) -> list[tuple[str, str]]:
    root = _root(path)
    rows = [("drive", root.name)]
    for name in (IMU_TO_VELO, "calib_velo_to_cam.txt"):
        found = [str(f / name) for f in (root, root.parent) if (f / name).is_file()]
        rows.append((name, found[0] if found else "missing"))
    return rows


DESCRIPTION = "KITTI raw drive (_sync): velodyne_points scans, OXTS poses in the LiDAR frame"

FORMAT = trajectory_format(TrajectoryFormat(
    name="kitti-raw", description=DESCRIPTION, read=read_drive, suffixes=("/",), sniff=_sniff("oxts"),
    describe=describe,
))

scan_source(ScanSource(
    name="kitti-raw", description=DESCRIPTION, open=open_drive, suffixes=("/",), sniff=_sniff("velodyne_points"),
    describe=describe, sensor=SensorKind.LIDAR,
))
