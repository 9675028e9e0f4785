"""Folders of scan files: KITTI ``.bin``, PCD, PLY, ``.npy`` / ``.npz`` (one scan per file, loaded lazily).

A KITTI sequence folder works too: the scans are then taken from its ``velodyne/`` subfolder.
Files are in natural order (``frame2`` before ``frame10``; by value when every name is a number).
Timestamps, first that applies: ``ReadOptions.times`` (one per line, must match the scan count);
``times.txt`` in the scan folder or its parent when its count matches; the file names when all are
numbers (``1561645825.123456.pcd`` = seconds; integers of 10 or more digits = epoch time whose first
10 digits are seconds, so ms / µs / ns stamps all work; shorter integers are frame numbers); else none.

Per-point fields map to :class:`Scan`: intensity <- ``intensity``/``i``/``reflectivity``; point time <-
``time``/``t``/``time_stamp``/``timestamp``/``offset_time`` (floats are seconds, integers nanoseconds);
ring <- ``ring``/``channel``. Points with NaN or infinite coordinates are dropped.
"""

from __future__ import annotations

import os
import re
from decimal import Decimal
from pathlib import Path

import numpy as np

from dm2_backend.formats import ply
from dm2_backend.formats._npy import load_npy, load_npz
from dm2_backend.formats.pcd import read_pcd, write_pcd
from dm2_backend.formats.registry import ReadOptions, ScanSource, scan_source
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import check_kind

SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy", ".npz")
INTENSITY_FIELDS = ("intensity", "i", "reflectivity")
TIME_FIELDS = ("time", "t", "time_stamp", "timestamp", "offset_time")
RING_FIELDS = ("ring", "channel")

__all__ = ["read_scan_file", "write_bin", "write_pcd", "scan_files", "open_folder", "natural_key"]


def scan_from_fields(fields: dict[str, np.ndarray], source: str | Path) -> Scan:
    """A :class:`Scan` from named per-point columns (x, y, z required), NaN points dropped."""
    if not all(k in fields for k in "xyz"):
        raise InputError(source, f"no x y z fields (fields: {' '.join(fields) or 'none'})")
    columns = [np.asarray(fields[k], dtype=np.float64) for k in "xyz"]
    xyz = np.stack([c if c.ndim == 1 else c[:, 0] for c in columns], 1)
    keep = np.isfinite(xyz).all(axis=1)

    def pick(names: tuple[str, ...]) -> np.ndarray | None:
        name = next((n for n in names if n in fields and np.ndim(fields[n]) == 1), None)
        return None if name is None else np.asarray(fields[name])[keep]

    intensity, time, ring = pick(INTENSITY_FIELDS), pick(TIME_FIELDS), pick(RING_FIELDS)
    if time is not None:
        time = time.astype(np.float64) * (1e-9 if time.dtype.kind in "iu" else 1.0)
    scan = Scan(
        points=xyz[keep],
        intensity=None if intensity is None else intensity.astype(np.float32),
        point_time=time,
        ring=None if ring is None else ring.astype(np.int32),
    )
    if len(scan) == 0:
        raise InputError(source, "empty scan (no points with finite coordinates)")
    return scan


def read_bin(path: Path) -> Scan:
    """KITTI Velodyne scan: float32 x y z intensity per point."""
    size = path.stat().st_size
    if size % 16:
        raise InputError(path, f"size {size} bytes is not a multiple of 16 (float32 x y z intensity)")
    data = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    fields = {"x": data[:, 0], "y": data[:, 1], "z": data[:, 2], "intensity": data[:, 3]}
    return scan_from_fields(fields, path)


def write_bin(path: str | Path, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """Write a KITTI ``.bin`` scan (intensity 0 when not given)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    data = np.zeros((len(pts), 4), dtype="<f4")
    data[:, :3] = pts
    if intensity is not None:
        data[:, 3] = np.asarray(intensity, dtype=np.float32).reshape(-1)
    with atomic_write(path, "wb") as fh:
        fh.write(data.tobytes())


def read_numpy(path: Path) -> Scan:
    """``.npy`` / ``.npz`` (key ``data`` or the only key): an (N, 3+) array, column 4 = intensity, or a
    structured array with named fields. Headers are checked before reading; pickles are never loaded."""
    if path.suffix.lower() == ".npz":
        arrays = load_npz(path)
        keys = list(arrays)
        if "data" not in keys and len(keys) != 1:
            raise InputError(path, f"npz holds {len(keys)} arrays ({', '.join(keys)}), none named 'data'")
        arr = arrays["data" if "data" in keys else keys[0]]
    else:
        arr = load_npy(path)
    if arr.dtype.names:
        return scan_from_fields({n: arr[n].reshape(-1) for n in arr.dtype.names}, path)
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in "fiu":
        raise InputError(path, f"expected a numeric N x 3+ array, found shape {arr.shape} {arr.dtype}")
    fields = {"x": arr[:, 0], "y": arr[:, 1], "z": arr[:, 2]}
    if arr.shape[1] > 3:
        fields["intensity"] = arr[:, 3]
    return scan_from_fields(fields, path)


def read_ply(path: Path) -> Scan:
    """PLY through dm2's numpy reader (:mod:`dm2_backend.formats.ply`; open3d's C++ reader crashes on
    hostile headers and truncated data): every scalar vertex property is kept."""
    return scan_from_fields(ply.read_ply(path), path)


def read_pcd_scan(path: Path) -> Scan:
    return scan_from_fields(read_pcd(path)[1], path)


_READERS = {".bin": read_bin, ".pcd": read_pcd_scan, ".ply": read_ply, ".npy": read_numpy, ".npz": read_numpy}


def read_scan_file(path: str | Path) -> Scan:
    """One scan file of any supported kind; :class:`InputError` naming the file when bad."""
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(path, f"not a scan file (expected {', '.join(SCAN_SUFFIXES)})")
    if not path.is_file():
        raise InputError(path, "no such file")
    return reader(path)


def natural_key(name: str) -> list:
    """Sort key putting ``frame2`` before ``frame10``."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name) if t]


_NUMBER = re.compile(r"\d+(\.\d+)?")


def _list_scans(folder: Path) -> list[Path]:
    with os.scandir(folder) as it:
        return [Path(e.path) for e in it if e.is_file() and e.name.lower().endswith(SCAN_SUFFIXES)
                and not e.name.startswith(".")]


def _has_scans(folder: Path) -> bool:
    with os.scandir(folder) as it:
        return any(e.name.lower().endswith(SCAN_SUFFIXES) and e.is_file() for e in it)


def scan_folder_of(path: Path) -> Path:
    """The folder holding the scans: ``path`` itself or its ``velodyne/`` subfolder (KITTI)."""
    if path.is_dir() and not _has_scans(path) and (path / "velodyne").is_dir():
        return path / "velodyne"
    return path


def scan_files(path: str | Path) -> list[Path]:
    """The scan files of a folder in natural order; :class:`InputError` when none or of mixed kinds."""
    folder = scan_folder_of(Path(path))
    files = _list_scans(folder)
    if not files:
        raise InputError(path, f"no scan files ({', '.join(SCAN_SUFFIXES)}) in the folder")
    kinds = sorted({f.suffix.lower() for f in files})
    if len(kinds) > 1:
        counts = ", ".join(f"{sum(f.suffix.lower() == k for f in files)} {k}" for k in kinds)
        raise InputError(folder, f"the folder mixes scan file kinds ({counts}); keep one kind per folder")
    if all(_NUMBER.fullmatch(f.stem) for f in files):
        return sorted(files, key=lambda f: Decimal(f.stem))
    return sorted(files, key=lambda f: natural_key(f.name))


def stamps_from_names(files: list[Path]) -> np.ndarray | None:
    """Seconds from numeric file names (see the module doc), else None."""
    stems = [f.stem for f in files]
    if not stems or not all(_NUMBER.fullmatch(s) for s in stems):
        return None
    if all("." not in s for s in stems):
        digits = {len(s.lstrip("0") or "0") for s in stems}
        if min(digits) < 10:
            return None  # frame numbers, not times
        return np.array([_int_seconds(int(s)) for s in stems])
    return np.array([float(Decimal(s)) for s in stems])


def _int_seconds(value: int) -> float:
    scale = 10 ** max(0, len(str(value)) - 10)
    whole, frac = divmod(value, scale)
    return whole + frac / scale


def read_times(path: Path) -> tuple[np.ndarray, list[int]]:
    """One time (seconds) per line; blank and ``#`` lines skipped. Returns values and line numbers."""
    values, lines = [], []
    check_kind(path, folder_ok=False)
    with open(path, encoding="utf-8", errors="replace") as fh:
        for no, line in enumerate(fh, 1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            try:
                (value,) = (float(v) for v in text.split())
            except ValueError:
                raise InputError(path, f"expected one time in seconds per line, got {text[:40]!r}",
                                 line=no) from None
            if not np.isfinite(value):
                raise InputError(path, f"time {text!r} is not finite", line=no)
            values.append(value)
            lines.append(no)
    stamps = np.array(values, dtype=np.float64)
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        kind = "duplicate" if stamps[i] == stamps[i - 1] else "unsorted"
        raise InputError(path, f"{kind} time {stamps[i]!r} after {stamps[i - 1]!r}", line=lines[i])
    return stamps, lines


def find_timestamps(folder: Path, files: list[Path], options: ReadOptions) -> tuple[np.ndarray | None, str]:
    """Timestamps for the scans and where they came from (see the module doc)."""
    if options.times is not None:
        stamps, _ = read_times(Path(options.times))
        if len(stamps) != len(files):
            raise InputError(options.times, f"{len(stamps)} times for {len(files)} scans in {folder}")
        return stamps, str(options.times)
    for candidate in (folder / "times.txt", folder.parent / "times.txt"):
        if candidate.is_file():
            stamps, _ = read_times(candidate)
            if len(stamps) == len(files):
                return stamps, str(candidate)
    stamps = stamps_from_names(files)
    if stamps is not None:
        bad = np.flatnonzero(np.diff(stamps) <= 0)
        if len(bad):
            raise InputError(files[bad[0] + 1], "file name time equals the previous one")
        return stamps, "file names"
    return None, "none"


def open_folder(path: Path, options: ReadOptions) -> ScanSequence:
    files = scan_files(path)
    folder = files[0].parent
    stamps, origin = find_timestamps(folder, files, options)
    return ScanSequence(
        loader=lambda i: read_scan_file(files[i]),
        count=len(files),
        timestamps=stamps,
        source=str(path),
        meta={"files": files, "times_from": origin, "kind": files[0].suffix.lower()},
    )


def sniff(path: Path) -> bool:
    return path.is_dir() and _has_scans(scan_folder_of(path))


def describe(path: Path) -> list[tuple[str, str]]:
    files = scan_files(path)
    return [
        ("scan folder", str(files[0].parent)),
        ("scan files", f"{len(files)} x {files[0].suffix.lower()} ({files[0].name} .. {files[-1].name})"),
    ]


scan_source(ScanSource(
    name="folder",
    description="folder of scan files (KITTI .bin, .pcd, .ply, .npy/.npz), also a KITTI velodyne/ folder",
    open=open_folder,
    suffixes=("/",),
    sniff=sniff,
    describe=describe,
))


def open_file(path: Path, options: ReadOptions) -> ScanSequence:
    """A single scan file as a one-scan sequence (for ``dm2 info`` on one file)."""
    scan = read_scan_file(path)
    return ScanSequence(loader=lambda i: scan, count=1, source=str(path),
                        planar=bool(len(scan.points)) and bool(np.abs(scan.points[:, 2]).max() < 1e-9))


scan_source(ScanSource(
    name="scan",
    description="a single scan file (KITTI .bin, .pcd, .ply, .npy/.npz)",
    open=open_file,
    suffixes=SCAN_SUFFIXES,
))
