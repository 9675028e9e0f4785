"""CARMEN log parsing: message lines (FLASER, ROBOTLASER1, RAWLASER*, ODOM, PARAM) into :class:`Message` records
and whole logs (plain, ``.gz``, ``.bz2``) into a :class:`CarmenLog`, cached by path, size and mtime. The message
formats, laser offsets and timestamps are described in :mod:`dm2_backend.formats.carmen`.
"""

from __future__ import annotations

import bz2
import gzip
import io
import math
import re
import zlib
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import check_kind

SUFFIXES = (".clf", ".log", ".clf.gz", ".log.gz", ".clf.bz2", ".log.bz2")
POSE_KINDS = ("FLASER", "ROBOTLASER1")
RAW_KINDS = ("RAWLASER", "RAWLASER1", "RAWLASER2", "RAWLASER3", "RAWLASER4")
LASER_KINDS = POSE_KINDS + RAW_KINDS
SCAN_ORDER = ("FLASER", "ROBOTLASER1", "RAWLASER1", "RAWLASER", "RAWLASER2", "RAWLASER3", "RAWLASER4")
TRAJ_ORDER = ("FLASER", "ROBOTLASER1", "ODOM")
FRONT_KINDS = ("FLASER", "ROBOTLASER1", "RAWLASER", "RAWLASER1")
KNOWN_NAMES = frozenset(
    LASER_KINDS + ("ODOM", "PARAM", "SYNC", "TRUEPOS", "RLASER", "ROBOTLASER2", "NMEAGGA", "NMEARMC",
                   "NMEA-GGA", "GPSNMEA", "SONAR", "BUMPER", "SCANMARK", "POSITIONLASER", "NEFF", "LASER")
)
CARMEN_MAX_RANGE = 80.0
#: largest log accepted (decompressed bytes): the Intel log, among the longest public ones, is 16 MiB
MAX_LOG_BYTES = 512 << 20
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_\-]*\Z")
_TOKEN = re.compile(r"\S+")


@dataclass(slots=True)
class Message:
    """One parsed laser or ODOM message; poses are ``(x, y, theta)``."""

    kind: str
    line: int | None
    timestamp: float
    host: str
    logger_timestamp: float | None = None
    ranges: np.ndarray | None = None
    remissions: np.ndarray | None = None
    start_angle: float = -math.pi / 2
    angular_resolution: float = math.pi / 180
    max_range: float | None = None
    laser_pose: tuple[float, float, float] | None = None
    robot_pose: tuple[float, float, float] | None = None
    #: index (in the line's words) of the first pose value the writer may replace
    pose_token: int | None = None


@dataclass
class CarmenLog:
    path: Path
    messages: dict[str, list[Message]]
    params: dict[str, str]
    counts: Counter = field(default_factory=Counter)


def flaser_angles(n: int) -> tuple[float, float]:
    """``(start_angle, angular_resolution)`` CARMEN assumes for an FLASER message with ``n`` beams."""
    if n in (180, 181):
        return -math.pi / 2, math.pi / 180
    if n in (360, 361):
        return -math.pi / 2, math.pi / 360
    if n in (400, 401):
        return -math.pi / 2, math.pi / 720
    return -math.pi / 2, (math.pi / (n - 1) if n > 1 else 0.0)


# ---------------------------------------------------------------- line parser


def _err(source, line, problem) -> InputError:
    return InputError(source, problem, line=line)


def _num(tok: str, what: str, source, line) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise _err(source, line, f"{what}: {tok!r} is not a number") from None
    if not math.isfinite(v):
        raise _err(source, line, f"{what} is {tok!r} (NaN or infinite)")
    return v


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _int(tok: str, what: str, source, line) -> int:
    try:
        v = int(tok)
    except ValueError:
        raise _err(source, line, f"{what}: {tok!r} is not an integer") from None
    if v < 0:
        raise _err(source, line, f"{what} is negative ({v})")
    return v


def _array(tokens: list[str], what: str, source, line) -> np.ndarray:
    try:
        a = np.array(tokens, dtype=np.float64)
    except ValueError:
        for t in tokens:
            _num(t, what, source, line)
        raise _err(source, line, f"{what} are not all numbers") from None
    if not np.isfinite(a).all():
        bad = tokens[int(np.argmax(~np.isfinite(a)))]
        raise _err(source, line, f"{what} contain {bad!r} (NaN or infinite)")
    return a.astype(np.float32)


def _pose(tokens: list[str], i: int, what: str, source, line) -> tuple[float, float, float]:
    return tuple(_num(tokens[i + k], f"{what} {'x y theta'.split()[k]}", source, line) for k in range(3))


def _tail(
    tokens: list[str], k: int, kind: str, n: int | None, source, line
) -> tuple[float, str, float | None]:
    """Check the word count (``k`` words before the ipc timestamp) and parse the timestamps."""
    counts = f" for num_readings={n}" if n is not None else ""
    problem = f"{kind}{counts} needs {k + 3} words (or {k + 2} without the logger timestamp), the line has "
    if len(tokens) not in (k + 2, k + 3):
        raise _err(source, line, problem + str(len(tokens)))
    if len(tokens) == k + 2 and not _is_number(tokens[k]):
        where = f"{len(tokens)} with {tokens[k]!r} where the ipc_timestamp belongs"
        raise _err(source, line, problem + where)
    ts = _num(tokens[k], "ipc_timestamp", source, line)
    logger = _num(tokens[k + 2], "logger_timestamp", source, line) if len(tokens) == k + 3 else None
    return ts, tokens[k + 1], logger


def _need(tokens: list[str], k: int, kind: str, source, line) -> None:
    if len(tokens) <= k:
        raise _err(source, line, f"{kind} is truncated ({len(tokens)} words)")


def _parse_flaser(tokens, source, line) -> Message:
    _need(tokens, 1, "FLASER", source, line)
    n = _int(tokens[1], "num_readings", source, line)
    k = 2 + n + 6
    if len(tokens) not in (k + 2, k + 3):
        _tail(tokens, k, "FLASER", n, source, line)
    ranges = _array(tokens[2:2 + n], "ranges", source, line)
    ts, host, logger = _tail(tokens, k, "FLASER", n, source, line)
    start, step = flaser_angles(n)
    return Message(
        "FLASER", line, ts, host, logger, ranges, None, start, step, None,
        _pose(tokens, 2 + n, "laser pose", source, line), _pose(tokens, 5 + n, "odometry pose", source, line),
        2 + n,
    )


def _parse_config_laser(tokens, kind, source, line) -> tuple[Message, int]:
    _need(tokens, 8, kind, source, line)
    _int(tokens[1], "laser_type", source, line)
    start, _fov, step, max_range, _acc = (
        _num(tokens[i], name, source, line)
        for i, name in enumerate(("start_angle", "fov", "angular_resolution", "maximum_range", "accuracy"), 2)
    )
    if abs(start) > 4 * math.pi or abs(step) > 2 * math.pi:
        raise _err(source, line, f"start_angle {start:g} / angular_resolution {step:g} rad are not beam angles")
    _int(tokens[7], "remission_mode", source, line)
    n = _int(tokens[8], "num_readings", source, line)
    _need(tokens, 9 + n, kind, source, line)
    _int(tokens[9 + n], "num_remissions", source, line)
    msg = Message(kind, line, 0.0, "", None, None, None, start, step, max_range)
    return msg, n


def _parse_robotlaser(tokens, source, line) -> Message:
    msg, n = _parse_config_laser(tokens, "ROBOTLASER1", source, line)
    m = int(tokens[9 + n])
    k = 10 + n + m + 11
    if len(tokens) not in (k + 2, k + 3):
        _tail(tokens, k, "ROBOTLASER1", n, source, line)
    msg.ranges = _array(tokens[9:9 + n], "ranges", source, line)
    msg.remissions = _array(tokens[10 + n:10 + n + m], "remissions", source, line)
    p = 10 + n + m
    msg.laser_pose = _pose(tokens, p, "laser pose", source, line)
    msg.robot_pose = _pose(tokens, p + 3, "robot pose", source, line)
    for i, name in enumerate(("tv", "rv", "forward_safety_dist", "side_safety_dist", "turn_axis")):
        _num(tokens[p + 6 + i], name, source, line)
    msg.pose_token = p
    msg.timestamp, msg.host, msg.logger_timestamp = _tail(tokens, k, "ROBOTLASER1", n, source, line)
    return msg


def _parse_rawlaser(tokens, source, line) -> Message:
    kind = tokens[0]
    msg, n = _parse_config_laser(tokens, kind, source, line)
    m = int(tokens[9 + n])
    k = 10 + n + m
    if len(tokens) not in (k + 2, k + 3):
        _tail(tokens, k, kind, n, source, line)
    msg.ranges = _array(tokens[9:9 + n], "ranges", source, line)
    msg.remissions = _array(tokens[10 + n:k], "remissions", source, line)
    msg.timestamp, msg.host, msg.logger_timestamp = _tail(tokens, k, kind, n, source, line)
    return msg


def _parse_odom(tokens, source, line) -> Message:
    ts, host, logger = _tail(tokens, 7, "ODOM", None, source, line)
    pose = _pose(tokens, 1, "odometry", source, line)
    for i, name in enumerate(("tv", "rv", "accel")):
        _num(tokens[4 + i], name, source, line)
    return Message("ODOM", line, ts, host, logger, robot_pose=pose, pose_token=1)


_PARSERS = {"FLASER": _parse_flaser, "ROBOTLASER1": _parse_robotlaser, "ODOM": _parse_odom}
_PARSERS.update({k: _parse_rawlaser for k in RAW_KINDS})


def parse_line(line: str, lineno: int | None = None, source: str | Path | None = None) -> Message | None:
    """Parse one log line: a :class:`Message` for laser/ODOM lines, ``None`` for comments, blank lines
    and other messages; :class:`InputError` naming ``source:lineno`` for malformed ones."""
    tokens = line.split()
    if not tokens or tokens[0].startswith("#"):
        return None
    parser = _PARSERS.get(tokens[0])
    if parser is not None:
        return parser(tokens, source, lineno)
    if not _NAME.match(tokens[0]):
        raise _err(source, lineno, f"not a CARMEN message: the line starts with {tokens[0][:40]!r}")
    return None


# ---------------------------------------------------------------- whole logs


def read_text(path: str | Path) -> str:
    """The log's text (gzip / bzip2 detected from the magic bytes), decoded as latin-1 (byte-preserving)."""
    path = Path(path)
    check_kind(path)
    try:
        with open(path, "rb") as fh:
            magic = fh.read(3)
        opener = gzip.open if magic[:2] == b"\x1f\x8b" else bz2.open if magic == b"BZh" else open
        with opener(path, "rb") as fh:
            data = fh.read(MAX_LOG_BYTES + 1)  # a bound: a small compressed file may expand without one
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a CARMEN log") from None
    except (OSError, EOFError, ValueError, zlib.error) as exc:  # gzip/bz2/zlib's errors for corrupt streams
        raise InputError(path, f"cannot decompress ({exc or 'truncated stream'})") from None
    if len(data) > MAX_LOG_BYTES:
        raise InputError(path, f"log larger than {MAX_LOG_BYTES >> 20} MiB (decompressed)")
    return data.decode("latin-1")


def _loadtxt(rows: list[str]) -> np.ndarray | None:
    """All-finite (L, C) float64 table of equally long numeric rows, or ``None`` (then parse line by line)."""
    try:
        a = np.loadtxt(io.StringIO("\n".join(rows)), dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        return None
    return a if a.shape[0] == len(rows) and np.isfinite(a).all() else None


def _bulk_flaser(lines: list[str], idx: list[int]) -> list[Message] | None:
    """Fast path for well-formed FLASER lines with the logger timestamp (numpy's C parser)."""
    rows, stamps, hosts = [], [], []
    for i in idx:
        parts = lines[i][7:].rsplit(None, 2)
        if len(parts) != 3:
            return None
        body, host, logger = parts
        rows.append(body + " " + logger)
        stamps.append(body[body.rfind(" ") + 1:])
        hosts.append(host)
    a = _loadtxt(rows)
    if a is None:
        return None
    n = a.shape[1] - 9
    if n < 0 or not (a[:, 0] == n).all():
        return None
    try:
        ts = [float(t) for t in stamps]
    except ValueError:
        return None
    ranges = a[:, 1:n + 1].astype(np.float32)
    poses = a[:, n + 1:n + 7].tolist()
    start, step = flaser_angles(n)
    return [
        Message("FLASER", i + 1, t, h, float(a[k, -1]), ranges[k], None, start, step, None,
                tuple(poses[k][:3]), tuple(poses[k][3:]), 2 + n)
        for k, (i, t, h) in enumerate(zip(idx, ts, hosts, strict=True))
    ]


def _bulk_odom(lines: list[str], idx: list[int]) -> list[Message] | None:
    rows, stamps, hosts = [], [], []
    for i in idx:
        words = lines[i].split()
        if len(words) != 10:
            return None
        rows.append(" ".join(words[1:8]) + " " + words[9])
        stamps.append(words[7])
        hosts.append(words[8])
    a = _loadtxt(rows)
    if a is None or a.shape[1] != 8:
        return None
    try:
        ts = [float(t) for t in stamps]
    except ValueError:
        return None
    poses = a[:, :3].tolist()
    return [
        Message("ODOM", i + 1, t, h, float(a[k, -1]), robot_pose=tuple(poses[k]), pose_token=1)
        for k, (i, t, h) in enumerate(zip(idx, ts, hosts, strict=True))
    ]


def parse_log(path: str | Path) -> CarmenLog:
    """Parse a whole log; use :func:`load` for the cached version."""
    path = Path(path)
    messages: dict[str, list[Message]] = {}
    params: dict[str, str] = {}
    counts: Counter = Counter()
    lines = read_text(path).split("\n")
    flaser: dict[str, list[int]] = {}
    odom: list[int] = []
    errors: list[InputError] = []
    for i, line in enumerate(lines):
        if line.startswith("FLASER "):
            flaser.setdefault(line[7:line.find(" ", 7)], []).append(i)
            continue
        if line.startswith("ODOM "):
            odom.append(i)
            continue
        try:
            msg = parse_line(line, i + 1, path)
        except InputError as exc:
            errors.append(exc)
            continue
        if msg is not None:
            messages.setdefault(msg.kind, []).append(msg)
            continue
        words = line.split(None, 3)
        if words and not words[0].startswith("#"):
            counts[words[0]] += 1
            if words[0] == "PARAM" and len(words) >= 3:
                params[words[1]] = words[2]
    for bulk, idx in [(_bulk_flaser, g) for g in flaser.values()] + [(_bulk_odom, odom)]:
        if not idx:
            continue
        try:
            parsed = bulk(lines, idx) or [parse_line(lines[i], i + 1, path) for i in idx]
        except InputError as exc:
            errors.append(exc)
            continue
        messages.setdefault(parsed[0].kind, []).extend(parsed)
    if errors:
        raise min(errors, key=lambda e: e.line or 0)
    for kind, msgs in messages.items():
        msgs.sort(key=lambda m: m.line)
        counts[kind] = len(msgs)
    if not any(k in messages for k in LASER_KINDS + ("ODOM",)):
        raise InputError(path, "no laser or ODOM messages: not a CARMEN log, or an empty one")
    return CarmenLog(path, messages, params, counts)


_CACHE: OrderedDict = OrderedDict()


def load(path: str | Path) -> CarmenLog:
    """Parsed log, cached by path, size and modification time (the last four logs)."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        raise InputError(path, "no such file") from None
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _CACHE:
        _CACHE[key] = parse_log(path)
        while len(_CACHE) > 4:
            _CACHE.popitem(last=False)
    _CACHE.move_to_end(key)
    return _CACHE[key]
