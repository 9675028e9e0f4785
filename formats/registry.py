"""Registry of trajectory formats and scan sources, with detection from path and content.

Each adapter module registers itself with :func:`trajectory_format` / :func:`scan_source`;
``dm2_backend.formats`` imports them all.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.kernel.scans import ScanSequence, SensorKind
from dm2_backend.kernel.trajectory import Trajectory, validate_poses, validate_timestamps
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import check_kind


@dataclass
class ReadOptions:
    """Options a reader may use; each reader ignores those that do not apply to it."""

    topic: str | None = None
    times: Path | None = None
    calib: Path | None = None
    #: depth camera intrinsics fx fy cx cy, and depth units per metre (None: the layout's own default)
    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float | None = None
    #: CARMEN: which pose the trajectory reader returns, "odometry" or "logged"
    pose_source: str = "logged"
    #: text trajectories (TUM, EuRoC, CARMEN, NCLT): a repeated timestamp is kept as evo keeps it ("keep"),
    #: only its first pose kept ("keep-first") or an error ("error")
    duplicate_times: str = "keep"
    #: depth sequences: every ``stride``-th pixel in each direction (None: the reader's default)
    stride: int | None = None
    #: depth sequences: smooth each pixel's depth over its neighbours on the same surface (False: as recorded)
    smooth_depth: bool = False
    #: CARMEN: the laser's pose in the robot frame (x, y, theta; None: the log's PARAMs or messages), ranges
    #: beyond ``max_range`` (m; None: the message's own) and below ``min_range`` (m) dropped
    laser_offset: tuple[float, float, float] | None = None
    max_range: float | None = None
    min_range: float = 0.0
    #: CARMEN writer: the log whose messages get the poses (None: the trajectory's own ``carmen_template``),
    #: which message type, whether ODOM lines are rewritten too, and whether 3D poses are flattened to x, y, yaw
    template: Path | None = None
    message: str | None = None
    overwrite_odometry: bool = False
    force_planar: bool = False
    #: options of third-party formats (dm2's own readers use only the fields above)
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class TrajectoryFormat:
    name: str
    description: str
    read: Callable[[Path, ReadOptions], Trajectory]
    write: Callable[[Trajectory, Path, ReadOptions], None] | None = None
    #: lower-case suffixes (".txt", ".bag", ".clf.gz") or "/" for a folder
    suffixes: tuple[str, ...] = ()
    #: content test for paths whose suffix is shared with other formats
    sniff: Callable[[Path], bool] | None = None
    #: extra facts for ``dm2 info`` (e.g. a bag's topics): rows of (key, value)
    describe: Callable[[Path], list[tuple[str, str]]] | None = None
    #: the format's reader refuses decreasing timestamps, so the writer must never get them
    ordered_stamps: bool = True
    #: the format's reader accepts repeated timestamps by default (else the writer must not get them either)
    repeated_stamps: bool = False
    #: the format stores timestamps (KITTI poses, g2o, .npy do not: a trajectory's stamps are not written, and
    #: a writer of a stamped format given none invents them; ``dm2 convert`` says so)
    stamped: bool = True


@dataclass(frozen=True)
class ScanSource:
    name: str
    description: str
    open: Callable[[Path, ReadOptions], ScanSequence]
    suffixes: tuple[str, ...] = ()
    sniff: Callable[[Path], bool] | None = None
    describe: Callable[[Path], list[tuple[str, str]]] | None = None
    #: the sensor its scans come from when the source knows (``ScanSequence.sensor``); None: the source cannot
    #: tell (a folder of scan files, a bag of either message), ``pipeline.inputs`` decides once from the scans'
    #: geometry (``SensorKind.of_geometry``)
    sensor: SensorKind | None = None


TRAJECTORY_FORMATS: dict[str, TrajectoryFormat] = {}
SCAN_SOURCES: dict[str, ScanSource] = {}


def trajectory_format(fmt: TrajectoryFormat) -> TrajectoryFormat:
    TRAJECTORY_FORMATS[fmt.name] = fmt
    return fmt


def scan_source(src: ScanSource) -> ScanSource:
    SCAN_SOURCES[src.name] = src
    return src


def _suffix_matches(path: Path, suffixes: tuple[str, ...]) -> bool:
    name = path.name.lower()
    if path.is_dir():
        return "/" in suffixes
    return any(name.endswith(s) for s in suffixes if s != "/")


def _detect(path: Path, table: dict, kind: str) -> str:
    if check_kind(path) is None:  # a FIFO, a device or a symlink loop: one line, never opened
        raise InputError(path, "no such file or folder")
    by_suffix = [f for f in table.values() if _suffix_matches(path, f.suffixes)]
    if len(by_suffix) == 1 and by_suffix[0].sniff is None:
        return by_suffix[0].name
    candidates = by_suffix or list(table.values())
    sniffed = [f.name for f in candidates if f.sniff is not None and _safe_sniff(f.sniff, path)]
    if len(sniffed) == 1:
        return sniffed[0]
    if len(sniffed) > 1:
        raise InputError(path, f"ambiguous {kind} format; say which with --format ({', '.join(sniffed)})")
    choices = ", ".join(f.name for f in candidates)
    raise InputError(path, f"unknown {kind} format; say which with --format ({choices})")


def _safe_sniff(sniff: Callable[[Path], bool], path: Path) -> bool:
    try:
        return bool(sniff(path))
    except (OSError, ValueError, UnicodeDecodeError, InputError):
        return False


def detect_trajectory_format(path: str | Path) -> str:
    """The format name for ``path``; an :class:`InputError` naming the choices when ambiguous."""
    return _detect(Path(path), TRAJECTORY_FORMATS, "trajectory")


def detect_scan_source(path: str | Path) -> str:
    return _detect(Path(path), SCAN_SOURCES, "scan source")


def _lookup(table: dict, name: str, kind: str, path: Path):
    if name not in table:
        raise InputError(path, f"unknown {kind} format {name!r}; choices: {', '.join(sorted(table))}")
    return table[name]


def read_trajectory(path: str | Path, fmt: str | None = None, options: ReadOptions | None = None) -> Trajectory:
    path = Path(path)
    if check_kind(path) is None:  # a FIFO, a device or a symlink loop: one line, never opened
        raise InputError(path, "no such file or folder")
    name = fmt or detect_trajectory_format(path)
    traj = _lookup(TRAJECTORY_FORMATS, name, "trajectory", path).read(path, options or ReadOptions())
    traj.meta.setdefault("format", name)
    traj.meta.setdefault("source", str(path))
    return traj


def check_writable(traj: Trajectory, fmt: str, path: str | Path, stamps_written: bool | None = None) -> None:
    """:class:`InputError` naming the trajectory's source when ``fmt``'s own reader would refuse what its
    writer would write: non-finite or broken poses, non-finite stamps, and (for formats that need them
    ordered) decreasing or repeated stamps. What dm2 writes, dm2 reads. Stamps are checked only where they
    are written (``stamps_written``; default: the format stores them)."""
    spec = TRAJECTORY_FORMATS[fmt]
    source = traj.meta.get("source") or path
    stamps_written = spec.stamped if stamps_written is None else stamps_written
    try:
        validate_poses(traj.poses.copy(), source)  # a copy: validation snaps near-rotations in place
        if traj.timestamps is not None and stamps_written:
            if spec.ordered_stamps:
                validate_timestamps(traj.timestamps, source, duplicates_ok=spec.repeated_stamps)
            elif not np.isfinite(traj.timestamps).all():
                i = int(np.argmax(~np.isfinite(traj.timestamps)))
                raise InputError(source, f"timestamp {i} is not finite")
    except InputError as err:
        raise InputError(err.source, f"cannot write {fmt} {path}: {err.problem}", line=err.line) from None


def write_trajectory(
    traj: Trajectory, path: str | Path, fmt: str, options: ReadOptions | None = None
) -> None:
    path = Path(path)
    spec = _lookup(TRAJECTORY_FORMATS, fmt, "trajectory", path)
    if spec.write is None:
        writable = ", ".join(sorted(n for n, f in TRAJECTORY_FORMATS.items() if f.write))
        raise InputError(path, f"format {fmt!r} cannot be written; writable: {writable}")
    if len(traj) == 0:
        raise InputError(path, "no poses to write")
    options = options or ReadOptions()
    check_writable(traj, fmt, path, stamps_written=spec.stamped or bool(options.times))
    spec.write(traj, path, options)


#: read options whose effective value a scan source reports in its ``meta`` (its default when not given)
EFFECTIVE_OPTIONS = ("intrinsics", "depth_scale", "stride", "smoothing")


def _plain(value):
    """One spelling per value for a cache key: paths resolved, numbers as floats, sequences as lists."""
    if isinstance(value, Path):
        return str(value.resolve())
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, (tuple, list, np.ndarray)):
        return [_plain(v) for v in value]
    return value


def read_spec(fmt: str, path: Path, options: ReadOptions, effective: dict | None = None) -> dict:
    """Everything that determines what ``open_scans`` reads: the format, the resolved path and every option
    (paths resolved; ``extra`` included), normalised (``--intrinsics 1,2,3,4`` and ``"1 2 3 4"``, a depth
    scale given or left at the layout's default of the same value: one key), as JSON-ready values.
    ``effective``: the values the source used for :data:`EFFECTIVE_OPTIONS` (its ``meta``)."""
    spec = {"format": fmt, "path": str(Path(path).resolve())}
    spec.update({k: _plain(v) for k, v in vars(options).items() if k != "extra"})  # every declared field
    spec.update({k: _plain(v) for k, v in (effective or {}).items() if k in EFFECTIVE_OPTIONS})
    spec["extra"] = {k: _plain(v) for k, v in sorted(options.extra.items())}
    return spec


def open_scans(path: str | Path, fmt: str | None = None, options: ReadOptions | None = None) -> ScanSequence:
    path = Path(path)
    if check_kind(path) is None:  # a FIFO, a device or a symlink loop: one line, never opened
        raise InputError(path, "no such file or folder")
    name = fmt or detect_scan_source(path)
    options = options or ReadOptions()
    spec = _lookup(SCAN_SOURCES, name, "scan source", path)
    seq = spec.open(path, options)
    seq.read_spec = read_spec(name, path, options, seq.meta)
    seq.sensor = seq.sensor or spec.sensor
    if len(seq) == 0:
        raise InputError(seq.source or path, "holds no scans")
    seq.meta.setdefault("format", name)
    return seq


def format_for_output(path: str | Path) -> str:
    """Writable format implied by an output path's suffix (no content to sniff yet)."""
    path = Path(path)
    matched = {f.name: max((len(s) for s in f.suffixes if s != "/" and path.name.lower().endswith(s)), default=0)
               for f in TRAJECTORY_FORMATS.values() if f.write is not None}
    longest = max(matched.values(), default=0)
    names = [name for name, n in matched.items() if n and n == longest]  # the most specific name wins
    if len(names) == 1:
        return names[0]
    choices = ", ".join(names or sorted(n for n, f in TRAJECTORY_FORMATS.items() if f.write))
    raise InputError(path, f"cannot tell the output format from the name; say which with --to ({choices})")


#: entry-point group through which other packages add formats: each entry point names a module that registers
#: its formats with :func:`trajectory_format` / :func:`scan_source` when imported, e.g. in its pyproject.toml
#: ``[project.entry-points."dm2.formats"] my-lidar = "my_package.dm2_format"``
FORMAT_GROUP = "dm2.formats"


def load_third_party() -> list[str]:
    """Import the modules of the ``dm2.formats`` entry points; one that fails to import is logged and skipped
    (a broken add-on must not stop dm2 from reading its own formats). Returns the names loaded."""
    import logging
    from importlib.metadata import entry_points

    loaded = []
    for ep in entry_points(group=FORMAT_GROUP):
        try:
            ep.load()
        except Exception as exc:  # noqa: BLE001 (any error of someone else's module: reported, not fatal)
            logging.getLogger(__name__).warning("format add-on %s (%s) not loaded: %s", ep.name, ep.value, exc)
            continue
        loaded.append(ep.name)
    return loaded
