"""NCLT sessions (University of Michigan North Campus Long-Term dataset), in their published layout.

A session folder (``2012-01-08/``, give this path) holds ``velodyne_sync/<utime>.bin`` and the sensor CSVs
(``odometry_mu_100hz.csv``, ``odometry_mu.csv``); ``groundtruth_<date>.csv`` is looked up in the session
folder, its parent, or a ``ground_truth/`` folder in either.

- Scans: per point little-endian uint16 x, y, z, uint8 intensity, uint8 laser id (8 bytes); metres are
  ``value * 0.005 - 100``. The laser id becomes :attr:`Scan.ring` (HDL-32E firing order, not elevation
  order). Stamps are the file names, microseconds (``utime``).
- Poses: CSV rows ``utime, x, y, z, roll, pitch, yaw`` (metres, radians, ``R = Rz(yaw) Ry(pitch) Rx(roll)``)
  of the body frame in the session's fixed world frame (kept as published: NCLT's world frame is shared
  by all sessions). Rows with NaN (the first ground-truth rows often are) are dropped and listed in
  ``meta["dropped_nan_lines"]``. Poses are expressed in the Velodyne frame, ``T_w_vel = T_w_body @
  T_body_vel``, with the published ``x_body_vel`` = (0.002, -0.004, -0.957) m, roll 0.807, pitch 0.166,
  yaw -90.703 degrees.
- Formats: ``nclt`` (session folder: the ground truth, sampled at the scan stamps when ``velodyne_sync/`` is
  there: linear positions and slerp between the two nearest rows, held up to 0.1 s past either end; scans
  further out get no pose), ``nclt-odometry`` (the same for the wheel/IMU odometry; also carried by the scan
  source as the warm start) and ``nclt-csv`` (one CSV file, its own rows).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dm2_backend.formats import _text
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import Scan, ScanSequence, SensorKind
from dm2_backend.kernel.trajectory import Trajectory, validate_timestamps
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

SCALE = 0.005  # m per count
OFFSET = -100.0  # m
POINT = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"), ("laser", "u1")])
#: x y z (m), roll pitch yaw (degrees) of the Velodyne in the body frame
X_BODY_VEL = (0.002, -0.004, -0.957, 0.807, 0.166, -90.703)
T_BODY_VEL = se3.make_poses(se3.rpy_to_matrix(np.deg2rad(X_BODY_VEL[3:])), X_BODY_VEL[:3])
ODOMETRY_FILES = ("odometry_mu_100hz.csv", "odometry_mu.csv")
#: a pose is held this long (s) before the first / after the last row when sampling at scan stamps
HOLD = 0.1
COLUMNS = "utime, x, y, z, roll, pitch, yaw"


# ---- scans -------------------------------------------------------------------------------------------

def read_nclt_bin(path: str | Path) -> Scan:
    """One ``velodyne_sync`` scan (see the module docstring)."""
    path = Path(path)
    size = path.stat().st_size
    if size % POINT.itemsize:
        raise InputError(path, f"size {size} bytes is not a multiple of 8 (uint16 x y z, uint8 intensity, laser)")
    data = np.fromfile(path, dtype=POINT)
    if len(data) == 0:
        raise InputError(path, "empty scan")
    xyz = np.stack([data[k] * SCALE + OFFSET for k in "xyz"], axis=1)
    return Scan(points=xyz, intensity=data["intensity"].astype(np.float32), ring=data["laser"].astype(np.int32))


def write_nclt_bin(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None,
                   laser: np.ndarray | None = None) -> None:
    """Write points (M,3) metres in the ``velodyne_sync`` packing (rounded to 5 mm)."""
    counts = np.rint((np.asarray(points, dtype=np.float64).reshape(-1, 3) - OFFSET) / SCALE)
    if counts.size and (counts.min() < 0 or counts.max() > np.iinfo(np.uint16).max):
        raise ValueError(f"coordinates outside [{OFFSET}, {OFFSET + 65535 * SCALE}] m cannot be packed")
    data = np.zeros(len(counts), dtype=POINT)
    for i, key in enumerate("xyz"):
        data[key] = counts[:, i]
    data["intensity"] = 0 if intensity is None else np.asarray(intensity).reshape(-1)
    data["laser"] = 0 if laser is None else np.asarray(laser).reshape(-1)
    with atomic_write(path, "wb") as fh:
        fh.write(data.tobytes())


def session_root(path: str | Path) -> Path | None:
    """The session folder of ``path`` (the session itself or its ``velodyne_sync/``), else None."""
    path = Path(path)
    if path.name == "velodyne_sync":
        path = path.parent
    if not path.is_dir():
        return None
    if (path / "velodyne_sync").is_dir() or any(path.glob("groundtruth_*.csv")) \
            or any((path / name).is_file() for name in ODOMETRY_FILES):
        return path
    return None


def _root(path: Path) -> Path:
    root = session_root(path)
    if root is None:
        raise InputError(path, "not an NCLT session folder (expected velodyne_sync/, groundtruth_*.csv or "
                               "odometry_mu_100hz.csv inside)")
    return root


def scan_stamps(root: Path) -> tuple[list[Path], np.ndarray]:
    """The ``velodyne_sync`` files in time order and their stamps (s)."""
    folder = root / "velodyne_sync"
    if not folder.is_dir():
        raise InputError(folder, "no such folder")
    files = [f for f in folder.iterdir() if f.suffix == ".bin" and not f.name.startswith(".")]
    if not files:
        raise InputError(folder, "no .bin scans")
    bad = next((f for f in files if not f.stem.isdigit()), None)
    if bad is not None:
        raise InputError(bad, "expected the scan time in microseconds as the file name (<utime>.bin)")
    files.sort(key=lambda f: int(f.stem))
    return files, np.asarray([int(f.stem) / 1e6 for f in files])


# ---- poses -------------------------------------------------------------------------------------------

def _parse_rows(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Rows (N,7) float64 and their line numbers: numpy's parser for clean files (a 100 Hz odometry has
    half a million rows), a line-by-line one that names the bad line otherwise."""
    try:
        with warnings.catch_warnings():  # an empty file: the line-by-line parser says so
            warnings.simplefilter("ignore", UserWarning)
            data = np.loadtxt(path, delimiter=",", ndmin=2, comments=None)
        raw = path.read_bytes()
        if data.shape[1] == 7 and len(data) == raw.count(b"\n") + (not raw.endswith(b"\n")):
            return data, np.arange(1, len(data) + 1)
    except (ValueError, UnicodeDecodeError, OSError):
        pass
    rows, lines = [], []
    for number, fields in _text.data_lines(_text.open_text(path)):
        if len(fields) != 7:
            raise InputError(path, _text.count_problem(len(fields), (7,), COLUMNS), line=number)
        rows.append(fields)
        lines.append(number)
    if not rows:
        raise InputError(path, f"no {COLUMNS} lines (empty file?)")
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:
        for number, fields in zip(lines, rows):
            bad = next((f for f in fields if not _text.is_float(f)), None)
            if bad is not None:
                raise InputError(path, f"not a number: {bad!r}", line=number) from None
        raise
    return data, np.asarray(lines)


def read_nclt_csv(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """A ground-truth or odometry CSV in the Velodyne frame (see the module docstring)."""
    path = Path(path)
    options = options or ReadOptions()
    data, lines = _parse_rows(path)
    if not np.isfinite(data[:, 0]).all():
        raise InputError(path, "utime is not a number", line=int(lines[np.argmax(~np.isfinite(data[:, 0]))]))
    if np.isinf(data[:, 1:]).any():
        raise InputError(path, "infinite value", line=int(lines[np.argmax(np.isinf(data[:, 1:]).any(axis=1))]))
    nan = np.isnan(data[:, 1:]).any(axis=1)
    meta: dict = {"frame": "lidar", "source_frame": "body"}
    if nan.any():
        meta["dropped_nan_lines"] = [int(n) for n in lines[nan]]
        data, lines = data[~nan], lines[~nan]
        if not len(data):
            raise InputError(path, "every row has NaN values")
    stamps = data[:, 0] / 1e6
    if _text.duplicate_policy(options) == "keep-first":
        stamps, data, lines, dropped = _text.drop_duplicate_times(stamps, data, lines)
        if dropped:
            meta["dropped_duplicate_lines"] = dropped
    try:
        validate_timestamps(stamps, path, 0)
    except InputError as exc:
        raise InputError(path, exc.problem, line=int(lines[exc.line])) from None
    body = se3.make_poses(rpy_matrices(data[:, 4:7]), data[:, 1:4])
    return Trajectory(poses=body @ T_BODY_VEL, timestamps=stamps, meta=meta)


def rpy_matrices(rpy: np.ndarray) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (N,3,3), written out as NCLT's ``ssc_to_homo`` does (fast for 10^6 rows;
    Euler rotations need no further check)."""
    (cr, cp, ch), (sr, sp, sh) = np.cos(rpy).T, np.sin(rpy).T
    return np.stack([
        np.stack([ch * cp, -sh * cr + ch * sp * sr, sh * sr + ch * sp * cr], axis=-1),
        np.stack([sh * cp, ch * cr + sh * sp * sr, -ch * sr + sh * sp * cr], axis=-1),
        np.stack([-sp, cp * sr, cp * cr], axis=-1),
    ], axis=-2)


def write_nclt_csv(traj: Trajectory, path: str | Path) -> None:
    """Write Velodyne-frame poses as an NCLT CSV (body frame, microsecond utimes)."""
    if traj.timestamps is None:
        raise InputError(path, "NCLT CSV rows need timestamps")
    body = traj.poses @ se3.inverse(T_BODY_VEL)
    rpy = se3.matrix_to_rpy(body[:, :3, :3])
    with atomic_write(path) as fh:
        for t, T, angles in zip(traj.timestamps, body, rpy):
            fh.write(f"{round(t * 1e6)}," + ",".join(map(repr, [*T[:3, 3].tolist(), *angles.tolist()])) + "\n")


def sample_at(traj: Trajectory, stamps: np.ndarray, hold: float = HOLD) -> Trajectory:
    """``traj`` at ``stamps`` (linear positions, slerp), held ``hold`` s past its ends; stamps further
    out are left out (their count is ``meta["unposed_scans"]``)."""
    t = traj.timestamps
    keep = (stamps >= t[0] - hold) & (stamps <= t[-1] + hold)
    at = np.clip(stamps[keep], t[0], t[-1])
    if len(t) == 1:
        poses = np.repeat(traj.poses, len(at), axis=0)
    else:
        i = np.clip(np.searchsorted(t, at, side="right") - 1, 0, len(t) - 2)
        f = (at - t[i]) / (t[i + 1] - t[i])
        a, b = traj.poses[i], traj.poses[i + 1]
        turn = Rotation.from_matrix(np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3]).as_rotvec()
        rotations = a[:, :3, :3] @ Rotation.from_rotvec(turn * f[:, None]).as_matrix()  # slerp
        poses = se3.make_poses(rotations, a[:, :3, 3] + f[:, None] * (b[:, :3, 3] - a[:, :3, 3])).reshape(-1, 4, 4)
    meta = {**traj.meta, "sampled_at": "velodyne_sync stamps", "unposed_scans": int((~keep).sum())}
    return Trajectory(poses=poses, timestamps=stamps[keep], meta=meta)


def _groundtruth_candidates(root: Path) -> list[Path]:
    found: list[Path] = []
    for folder in (root, root / "ground_truth", root.parent, root.parent / "ground_truth"):
        if folder.is_dir():
            found += sorted(folder.glob("groundtruth_*.csv"))
    return found


def find_groundtruth(root: Path) -> Path:
    """``groundtruth_<session name>.csv`` or, failing that, the only ``groundtruth_*.csv`` near ``root``."""
    found = _groundtruth_candidates(root)
    named = [f for f in found if f.name == f"groundtruth_{root.name}.csv"]
    if named:
        return named[0]
    if len({f.name for f in found}) == 1:
        return found[0]
    if not found:
        raise InputError(root / f"groundtruth_{root.name}.csv", "missing ground truth (looked in the session "
                         "folder, its parent and ground_truth/ in either)")
    raise InputError(root, f"several ground truths ({', '.join(f.name for f in found)}) and none named "
                     f"groundtruth_{root.name}.csv; give the CSV itself")


def find_odometry(root: Path) -> Path:
    for name in ODOMETRY_FILES:
        if (root / name).is_file():
            return root / name
    raise InputError(root / ODOMETRY_FILES[0], f"missing odometry (looked for {' and '.join(ODOMETRY_FILES)})")


def _at_scans(traj: Trajectory, root: Path, source: Path) -> Trajectory:
    if not (root / "velodyne_sync").is_dir():
        return traj
    _, stamps = scan_stamps(root)
    sampled = sample_at(traj, stamps)
    if len(sampled) == 0:
        raise InputError(source, f"covers none of the {len(stamps)} scans (poses {traj.timestamps[0]:.3f} .. "
                         f"{traj.timestamps[-1]:.3f} s, scans {stamps[0]:.3f} .. {stamps[-1]:.3f} s)")
    return sampled


def _read_session_csv(path: str | Path, find, options: ReadOptions | None) -> Trajectory:
    root = _root(Path(path))
    csv = find(root)
    traj = _at_scans(read_nclt_csv(csv, options), root, csv)
    traj.meta["file"] = str(csv)
    return traj


def read_session(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """The session's ground truth in the Velodyne frame (at the scan stamps when there are scans)."""
    return _read_session_csv(path, find_groundtruth, options)


def read_session_odometry(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """The session's odometry in the Velodyne frame (at the scan stamps when there are scans)."""
    return _read_session_csv(path, find_odometry, options)


def open_session(path: Path, options: ReadOptions) -> ScanSequence:
    """The ``velodyne_sync`` scans; carries ``"odometry"`` (the warm start) when it covers every scan."""
    root = _root(path)
    files, stamps = scan_stamps(root)
    meta: dict = {"files": files, "times_from": "file names (utime)"}
    carried = {}
    odom = next((root / n for n in ODOMETRY_FILES if (root / n).is_file()), None)
    if odom is not None:
        traj = sample_at(read_nclt_csv(odom, options), stamps)
        if len(traj) == len(stamps):
            carried["odometry"] = traj
        else:
            meta["odometry"] = f"{odom.name} covers {len(traj)} of {len(stamps)} scans; not used"
    return ScanSequence(loader=lambda i: read_nclt_bin(files[i]), count=len(files), timestamps=stamps,
                        source=str(root), trajectories=carried, meta=meta)


# ---- detection -----------------------------------------------------------------------------------------

def sniff_session(path: Path) -> bool:
    return session_root(path) is not None


def sniff_scans(path: Path) -> bool:
    root = session_root(path)
    return root is not None and (root / "velodyne_sync").is_dir()


def sniff_csv(path: Path) -> bool:
    """Seven numeric comma-separated fields, the first a microsecond utime (16 digits)."""
    with open(path, encoding="utf-8") as fh:
        first = fh.readline().strip()
    fields = first.split(",")
    return len(fields) == 7 and fields[0].strip().isdigit() and len(fields[0].strip()) >= 15 \
        and all(_text.is_float(f) for f in fields)


def describe(path: Path) -> list[tuple[str, str]]:
    root = _root(path)
    rows = [("session", str(root))]
    if (root / "velodyne_sync").is_dir():
        rows.append(("velodyne_sync", f"{len(scan_stamps(root)[0])} scans"))
    for what, find in (("ground truth", find_groundtruth), ("odometry", find_odometry)):
        try:
            rows.append((what, str(find(root))))
        except InputError as err:
            rows.append((what, err.problem))
    return rows


DESCRIPTION = "NCLT session: velodyne_sync scans, ground truth in the Velodyne frame"

trajectory_format(TrajectoryFormat(
    name="nclt", description=DESCRIPTION, read=read_session, suffixes=("/",), sniff=sniff_session,
    describe=describe,
))
trajectory_format(TrajectoryFormat(
    name="nclt-odometry", description="NCLT session: odometry_mu_100hz.csv in the Velodyne frame (by --format)",
    read=read_session_odometry, describe=describe,
))
trajectory_format(TrajectoryFormat(
    name="nclt-csv", description="NCLT ground-truth / odometry CSV (utime, x, y, z, roll, pitch, yaw), Velodyne frame",
    read=read_nclt_csv, suffixes=(".csv",), sniff=sniff_csv,
))
scan_source(ScanSource(
    name="nclt", description=DESCRIPTION, open=open_session, suffixes=("/",), sniff=sniff_scans,
    describe=describe, sensor=SensorKind.LIDAR,
))
