"""CARMEN robot logs (``.clf`` / ``.log``, optionally ``.gz`` / ``.bz2``): 2D laser scans and poses.

Message layouts (white-space separated; every message ends ``ipc_timestamp ipc_hostname
logger_timestamp``, the logger timestamp being optional here):

* ``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta``
* ``ROBOTLASER1 laser_type start_angle fov angular_resolution maximum_range accuracy remission_mode
  n r_1..r_n m e_1..e_m laser_x laser_y laser_theta robot_x robot_y robot_theta
  tv rv forward_safety_dist side_safety_dist turn_axis``
* ``RAWLASER[1-4] laser_type start_angle fov angular_resolution maximum_range accuracy remission_mode
  n r_1..r_n m e_1..e_m`` (no pose)
* ``ODOM x y theta tv rv accel``; ``PARAM name value`` (the ``robot_frontlaser_*`` offsets are used).

Other messages (SYNC, TRUEPOS, NMEA*, NEFF, RLASER, ROBOTLASER2, ...) are skipped; a line whose first
word is not a message name is an error. Layouts match CARMEN's ``readlog.c``
(pblop/missionlab-carmen @ 7205affd, ``src/logger/readlog.c``:
``carmen_string_to_robot_laser_message[_orig]``, ``carmen_string_to_laser_laser_message``,
``carmen_string_to_base_odometry_message``) and the ROBOTLASER1
reader of the Freiburg Robot Mapping course (foreversuiyi/Robot-Mapping, ``tools/read_robotlaser.m``).

Conventions:

* Beam angles are ``start_angle + i * angular_resolution``. FLASER carries no angles; like CARMEN's
  ``carmen_laser_guess_angle_increment`` we use ``start = -pi/2`` and a step of 1 deg for 180/181 beams,
  0.5 deg for 360/361, 0.25 deg for 400/401, else ``pi / (n - 1)``: 180 beams cover -90..+89 deg (the
  logger dropped the SICK's 181st beam). GMapping (ros-perception/slam_gmapping @ 03b8eb26,
  ``openslam_gmapping/log/carmenconfiguration.cpp``) instead puts 180 beams at +-1..+-90 deg. Checked on the
  GMapping-corrected ACES/Intel logs: consecutive scans placed with the corrected poses agree best with
  CARMEN's angles (median point-to-nearest-point 4.3 / 3.0 cm) over GMapping's (4.6 / 3.2 cm), a centred
  -89.5..+89.5 deg (4.4 / 3.0 cm) or -90..+90 deg in 179 steps (4.4 / 3.0 cm).
* In FLASER/ROBOTLASER1, ``x y theta`` is the laser's pose in the world and ``odom_x..`` / ``robot_x..``
  the robot's (odometry) pose; the laser sits at ``robot (+) offset``, the offset being
  ``robot_frontlaser_offset`` / ``_side_offset`` / ``_angular_offset`` PARAMs (override with
  ``ReadOptions.laser_offset = (x, y, theta)``); without them 0, except for ROBOTLASER1, whose
  messages carry both poses: there the offset is ``robot_pose^-1 (+) laser_pose`` when every message agrees
  on it (a raw log written by CARMEN's robot module), so that a laser mounted ahead of the axle is not
  taken for the robot. In the Freiburg logs the offset is 0, so both
  poses are equal; in the GMapping "corrected" dialect both hold the corrected pose.
* Scans are returned in the ROBOT frame (offset applied), z = 0. Trajectories are robot poses:
  ``"odometry"`` = the robot pose fields, ``"logged"`` = laser pose (+) offset^-1. For RAWLASER both are the
  ODOM poses interpolated at the scan times. Timestamps are the ipc_timestamp, parsed with ``float()``.
* Readings ``<= min_range`` (0) or ``>= max_range`` are invalid and dropped. ``max_range``: the
  ``ReadOptions.max_range``, else the message's ``maximum_range`` field, else (FLASER) CARMEN's 80 m,
  lowered to the log's largest reading when that value repeats as a saturation value (ACES: 50 m).
* Log order is kept. Real logs have non-monotonic ipc timestamps (Intel: 631 steps back, up to 0.9 s, while
  the poses show file order is right) and duplicate ODOM stamps, so neither is an error here; the count of
  backward steps is in ``meta["unsorted_timestamps"]``.

Writing (:func:`write_carmen`): with a template log (``ReadOptions.template``, else the log the trajectory was
read from) only the pose fields of the matched laser messages change; without one, ODOM lines.
:func:`read_relations` reads the Freiburg benchmark ``.relations`` files.

``ReadOptions.topic`` picks the message kind (default FLASER, else ROBOTLASER1, else RAWLASER1/RAWLASER for
scans and ODOM for trajectories).
"""

from __future__ import annotations

import bz2
import gzip
import io
import itertools
import math
import re
import zlib
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.atomic import atomic_write
from dm2_backend.errors import InputError
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.geometry import se3
from dm2_backend.scans import Scan, ScanSequence
from dm2_backend.trajectory import Trajectory, validate_poses

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


def _pick(log: CarmenLog, wanted: str | None, order: tuple[str, ...], what: str) -> str:
    present = [k for k in log.messages]
    if wanted is not None:
        if wanted not in order or wanted not in log.messages:
            usable = ", ".join(k for k in order if k in log.messages) or "none"
            raise InputError(log.path, f"no {wanted} messages to read {what} from (usable here: {usable})")
        return wanted
    for kind in order:
        if kind in log.messages:
            return kind
    raise InputError(log.path, f"no messages to read {what} from (found {', '.join(present) or 'none'}; "
                               f"need one of {', '.join(order)})")


def laser_offset(log: CarmenLog, kind: str, options: ReadOptions | None = None) -> tuple[float, float, float]:
    """The laser's pose in the robot frame: ``ReadOptions.laser_offset``, else the front-laser PARAMs, else 0."""
    if options is not None and options.laser_offset is not None:
        x, y, th = (float(v) for v in options.laser_offset)
        return x, y, th
    if kind not in FRONT_KINDS:
        return 0.0, 0.0, 0.0
    if kind == "ROBOTLASER1" and not any(f"robot_frontlaser_{s}" in log.params
                                         for s in ("offset", "side_offset", "angular_offset")):
        return _message_offset(log.messages[kind])
    out = []
    for suffix in ("offset", "side_offset", "angular_offset"):
        text = log.params.get(f"robot_frontlaser_{suffix}", "0")
        try:
            out.append(float(text))
        except ValueError:
            raise InputError(log.path, f"PARAM robot_frontlaser_{suffix} {text!r} is not a number") from None
    return out[0], out[1], out[2]


def _message_offset(msgs: list[Message]) -> tuple[float, float, float]:
    """The laser's pose in the robot frame that ROBOTLASER1 messages imply (``laser_pose = robot_pose (+)
    offset``, as CARMEN's robot module writes them) when the log has no front-laser PARAMs: the median of
    ``robot_pose^-1 (+) laser_pose`` when it is the same in every message (within 1 cm and 0.5 deg), else 0 (the
    two poses come from different estimators, e.g. a corrected laser pose over raw odometry)."""
    rel = se3.to_xy_yaw(se3.relative(se3.from_xy_yaw(_xyyaw(msgs, "robot_pose")),
                                     se3.from_xy_yaw(_xyyaw(msgs, "laser_pose"))))
    if not len(rel):
        return 0.0, 0.0, 0.0
    med = np.median(rel, axis=0)
    spread = np.abs(rel - med)
    spread[:, 2] = np.abs(se3.wrap_angle(rel[:, 2] - med[2]))
    if spread[:, :2].max() > 0.01 or spread[:, 2].max() > math.radians(0.5):
        return 0.0, 0.0, 0.0
    return float(med[0]), float(med[1]), float(med[2])


def _xyyaw(msgs: list[Message], attr: str) -> np.ndarray:
    return np.array([getattr(m, attr) for m in msgs], dtype=np.float64).reshape(-1, 3)


def _interp_odometry(log: CarmenLog, stamps: np.ndarray) -> np.ndarray | None:
    odom = log.messages.get("ODOM")
    if not odom:
        return None
    t = np.array([m.timestamp for m in odom])
    p = _xyyaw(odom, "robot_pose")
    p[:, 2] = np.unwrap(p[:, 2])
    order = np.argsort(t, kind="stable")
    t, p = t[order], p[order]
    out = np.stack([np.interp(stamps, t, p[:, j]) for j in range(3)], axis=1)
    out[:, 2] = se3.wrap_angle(out[:, 2])
    return out


def robot_poses(log: CarmenLog, kind: str, options: ReadOptions | None = None) -> dict[str, np.ndarray]:
    """``{"odometry": (N,4,4), "logged": (N,4,4)}`` robot poses of the ``kind`` messages (empty when a
    RAWLASER log has no ODOM)."""
    msgs = log.messages[kind]
    if kind in POSE_KINDS:
        mount = se3.from_xy_yaw(np.array(laser_offset(log, kind, options)))
        odom = se3.from_xy_yaw(_xyyaw(msgs, "robot_pose"))
        logged = se3.from_xy_yaw(_xyyaw(msgs, "laser_pose")) @ se3.inverse(mount)
        return {"odometry": odom, "logged": logged}
    if kind == "ODOM":
        odom = se3.from_xy_yaw(_xyyaw(msgs, "robot_pose"))
        return {"odometry": odom, "logged": odom}
    interp = _interp_odometry(log, np.array([m.timestamp for m in msgs]))
    if interp is None:
        return {}
    odom = se3.from_xy_yaw(interp)
    return {"odometry": odom, "logged": odom}


def _validated(log: CarmenLog, kind: str, poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``poses`` after :func:`validate_poses` (finite, not absurdly far), an error naming the message's line."""
    msgs = log.messages[kind]
    for value in poses.values():
        try:
            validate_poses(value, log.path)
        except InputError as exc:
            m = re.match(r"pose (\d+)", exc.problem)
            line = msgs[int(m.group(1))].line if m and int(m.group(1)) < len(msgs) else None
            raise InputError(log.path, exc.problem, line=line) from None
    return poses


def _stamps(msgs: list[Message]) -> np.ndarray:
    return np.array([m.timestamp for m in msgs], dtype=np.float64)


def _meta(log: CarmenLog, kind: str, stamps: np.ndarray, options: ReadOptions) -> dict:
    return {
        "source": str(log.path),
        "carmen_message": kind,
        "carmen_template": str(log.path),
        "laser_offset": laser_offset(log, kind, options),
        "unsorted_timestamps": int((np.diff(stamps) < 0).sum()),
    }


def read_carmen(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Robot poses of the laser messages (or ODOM lines when there are none): ``options.pose_source``
    ``"logged"`` (default) or ``"odometry"``."""
    options = options or ReadOptions()
    log = load(path)
    if options.pose_source not in ("logged", "odometry"):
        raise InputError(path, f"pose source {options.pose_source!r}: choose 'logged' or 'odometry'")
    kind = _pick(log, options.topic, TRAJ_ORDER + RAW_KINDS, "poses")
    poses = _validated(log, kind, robot_poses(log, kind, options))
    if not poses:
        raise InputError(path, f"{kind} messages carry no pose and the log has no ODOM messages")
    msgs = log.messages[kind]
    stamps = _stamps(msgs)
    chosen = poses[options.pose_source]
    meta = _meta(log, kind, stamps, options)
    if options.duplicate_times == "keep-first":
        keep = np.ones(len(stamps), bool)
        keep[1:] = np.diff(stamps) != 0
        if not keep.all():
            meta["dropped_duplicate_lines"] = [msgs[i].line for i in np.flatnonzero(~keep)]
            chosen, stamps = chosen[keep], stamps[keep]
    return Trajectory(chosen, stamps, planar=True, meta=meta)


# ---------------------------------------------------------------- scans


def max_range(log: CarmenLog, kind: str, options: ReadOptions | None = None) -> float | None:
    """The range at or beyond which readings are invalid; ``None``: the per-message maximum_range field."""
    if options is not None and options.max_range is not None:
        return float(options.max_range)
    if kind != "FLASER":
        return None
    top = max((float(m.ranges.max()) for m in log.messages[kind] if len(m.ranges)), default=0.0)
    total = sum(len(m.ranges) for m in log.messages[kind])
    hits = sum(int((m.ranges == np.float32(top)).sum()) for m in log.messages[kind])
    if hits >= max(10, 1e-3 * total) and top < CARMEN_MAX_RANGE:
        return top
    return CARMEN_MAX_RANGE


def scan_points(msg: Message, offset: tuple[float, float, float], max_r: float | None,
                min_r: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """Valid readings of ``msg`` as (M,3) float32 points in the robot frame, and their remissions."""
    r = msg.ranges.astype(np.float64)
    limit = max_r if max_r is not None else msg.max_range
    valid = r > min_r
    if limit is not None and limit > 0:
        valid &= r < np.float32(limit)
    a = msg.start_angle + np.arange(len(r)) * msg.angular_resolution + offset[2]
    rv, av = r[valid], a[valid]
    pts = np.zeros((len(rv), 3), dtype=np.float32)
    pts[:, 0] = rv * np.cos(av) + offset[0]
    pts[:, 1] = rv * np.sin(av) + offset[1]
    rem = msg.remissions
    return pts, (rem[valid] if rem is not None and len(rem) == len(r) else None)


def open_carmen_scans(path: str | Path, options: ReadOptions | None = None) -> ScanSequence:
    """Lazy scans (robot frame, z = 0) of one laser message kind, with ``odometry`` and ``logged`` poses."""
    options = options or ReadOptions()
    log = load(path)
    kind = _pick(log, options.topic, SCAN_ORDER, "scans")
    msgs = log.messages[kind]
    offset = laser_offset(log, kind, options)
    max_r = max_range(log, kind, options)
    min_r = float(options.min_range)
    stamps = _stamps(msgs)
    meta = _meta(log, kind, stamps, options) | {"max_range": max_r, "min_range": min_r}
    trajs = {
        name: Trajectory(p, stamps.copy(), planar=True, meta=dict(meta, pose_source=name))
        for name, p in _validated(log, kind, robot_poses(log, kind, options)).items()
    }

    def loader(i: int) -> Scan:
        pts, rem = scan_points(msgs[i], offset, max_r, min_r)
        return Scan(pts, timestamp=msgs[i].timestamp, intensity=rem)

    return ScanSequence(
        loader, len(msgs), stamps, planar=True, source=str(path), trajectories=trajs, meta=meta
    )


# ---------------------------------------------------------------- writing


def _xyyaw_of(traj: Trajectory, path: Path, force_planar: bool) -> np.ndarray:
    if not force_planar and not se3.is_planar(traj.poses, tol=1e-3):
        raise InputError(path, "CARMEN logs are 2D but the trajectory is not planar (z, roll or pitch "
                               "above 1e-3); set ReadOptions.force_planar to drop them")
    return se3.to_xy_yaw(traj.poses)


def _match(traj: Trajectory, stamps: np.ndarray, path: Path) -> np.ndarray:
    """For each pose, the index of its template message (exact stamps, else by index when counts agree)."""
    n, m = len(traj), len(stamps)
    if traj.timestamps is None or m == 0:
        if n != m:
            raise InputError(path, f"{n} poses without timestamps for {m} template messages")
        return np.arange(n)
    t = traj.timestamps
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    pos = np.clip(np.searchsorted(s, t), 1, max(m - 1, 1)) if m > 1 else np.zeros(n, int)
    left = np.maximum(pos - 1, 0)
    best = np.where(np.abs(s[left] - t) <= np.abs(s[pos] - t), left, pos)
    ok = np.abs(s[best] - t) <= 5e-7 + 4 * np.spacing(np.abs(t))
    idx = order[best]
    if ok.all() and len(np.unique(idx)) == n:
        return idx
    if n == m and np.all(np.abs(t - stamps) < 1e-3):
        return np.arange(n)
    if not ok.all():
        i = int(np.argmax(~ok))
        raise InputError(path, f"pose {i} (timestamp {t[i]!r}) has no template message with that timestamp")
    _, first, counts = np.unique(idx, return_index=True, return_counts=True)
    i = int(first[np.argmax(counts > 1)])
    raise InputError(path, f"pose {i} (timestamp {t[i]!r}) shares its template message with another pose")


def _fmt(v: float) -> str:
    return f"{v:.6f}"


def write_carmen(
    path: str | Path,
    traj: Trajectory,
    template: str | Path | None = None,
    *,
    message: str | None = None,
    overwrite_odometry: bool = False,
    force_planar: bool = False,
    options: ReadOptions | None = None,
) -> None:
    """Write ``traj`` (robot poses) as a CARMEN log, gzip/bzip2-compressed by the suffix of ``path``.

    With a ``template`` log: each ``message`` (FLASER / ROBOTLASER1 / ODOM; default the template's first
    of these) gets the matching pose (by exact timestamp, else by index when the counts agree) written into
    its laser pose fields as ``pose (+) laser offset``, ``%.6f``; ``overwrite_odometry`` also sets the robot
    pose fields (the GMapping "corrected" dialect). Messages of that kind without a pose are dropped (as in
    a subsampled corrected log); every other byte is kept. Without a template: one
    ``ODOM x y theta 0 0 0 t dm2 t-t0`` line a pose (t = the pose index when there are no timestamps).
    """
    path = Path(path)
    xyt = _xyyaw_of(traj, path, force_planar)
    if template is None:
        text = _odom_only(traj, xyt)
    else:
        text = _rewrite(load(template), traj, path, message, overwrite_odometry, options)
    data = text.encode("latin-1")
    name = path.name.lower()
    if name.endswith(".gz"):
        data = gzip.compress(data, mtime=0)
    elif name.endswith(".bz2"):
        data = bz2.compress(data)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def _odom_only(traj: Trajectory, xyt: np.ndarray) -> str:
    stamps = traj.timestamps if traj.timestamps is not None else np.arange(len(traj), dtype=np.float64)
    t0 = float(stamps[0]) if len(stamps) else 0.0
    lines = [
        "# CARMEN log written by dm2: one pose per ODOM message",
        "# ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp",
    ]
    for (x, y, th), t in zip(xyt, stamps, strict=True):
        lines.append(f"ODOM {_fmt(x)} {_fmt(y)} {_fmt(th)} 0.000000 0.000000 0.000000 {float(t)!r} dm2 "
                     f"{_fmt(float(t) - t0)}")
    return "\n".join(lines) + "\n"


def _fields(new: np.ndarray, old: tuple[float, float, float]) -> list[str | None]:
    """Printed ``x y theta``; ``None`` keeps the template's text where it already says the same (< 5e-7)."""
    d = np.abs(np.asarray(new) - np.asarray(old))
    d[2] = abs(float(se3.wrap_angle(new[2] - old[2])))
    return [None if d[k] <= 5e-7 else _fmt(new[k]) for k in range(3)]


def _rewrite(log: CarmenLog, traj: Trajectory, path: Path, message: str | None, overwrite_odometry: bool,
             options: ReadOptions | None) -> str:
    kind = _pick(log, message, TRAJ_ORDER, "poses to replace")
    msgs = log.messages[kind]
    idx = _match(traj, _stamps(msgs), path)
    poses = traj.poses
    if kind in POSE_KINDS:
        mount = se3.from_xy_yaw(np.array(laser_offset(log, kind, options)))
        laser = se3.to_xy_yaw(poses @ mount)
    else:
        laser = se3.to_xy_yaw(poses)
    robot = se3.to_xy_yaw(poses)
    new_fields: dict[int, tuple[int, list[str | None]]] = {}
    for i, j in enumerate(idx):
        msg = msgs[j]
        values = _fields(laser[i], msg.laser_pose if kind in POSE_KINDS else msg.robot_pose)
        if overwrite_odometry and kind in POSE_KINDS:
            values += _fields(robot[i], msg.robot_pose)
        new_fields[msg.line] = (msg.pose_token, values)
    drop = {m.line for m in msgs} - set(new_fields)
    lines = read_text(log.path).split("\n")
    out = []
    offset = laser_offset(log, kind, options)
    if kind == "ROBOTLASER1" and any(offset) and not overwrite_odometry and not any(
            k.startswith("robot_frontlaser_") for k in log.params):
        # the offset came from the messages; once the laser poses are rewritten they no longer imply it, so
        # the output says it (CARMEN's PARAM lines), and reading it back gives the same robot poses
        t = msgs[0].timestamp
        out += [f"PARAM robot_frontlaser_{name} {v:.6f} {t!r} dm2 0.000000"
                for name, v in zip(("offset", "side_offset", "angular_offset"), offset, strict=True)]
    for no, line in enumerate(lines, start=1):
        if no in drop:
            continue
        if no in new_fields:
            first, values = new_fields[no]
            spans = [mt.span() for mt in itertools.islice(_TOKEN.finditer(line), first, first + len(values))]
            for (a, b), v in reversed(list(zip(spans, values, strict=True))):
                line = line if v is None else line[:a] + v + line[b:]
        out.append(line)
    return "\n".join(out)


# ---------------------------------------------------------------- relations, detection, registration


_RELATION_FIELDS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")


def read_relations(path: str | Path) -> np.ndarray:
    """Freiburg benchmark relations ``t1 t2 x y z roll pitch yaw`` as an (M, 8) float64 array."""
    path = Path(path)
    rows = []
    for no, line in enumerate(read_text(path).split("\n"), start=1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) != 8:
            raise InputError(
                path, f"a relation has 8 values (t1 t2 x y z roll pitch yaw), found {len(words)}", line=no
            )
        rows.append([_num(w, name, path, no) for w, name in zip(words, _RELATION_FIELDS, strict=True)])
    if not rows:
        raise InputError(path, "no relations")
    return np.array(rows, dtype=np.float64)


def sniff(path: str | Path) -> bool:
    """``.clf`` names are CARMEN; other names when the first message line starts with a CARMEN name."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith((".clf", ".clf.gz", ".clf.bz2")):
        return True
    try:
        with open(path, "rb") as fh:
            magic = fh.read(3)
        opener = gzip.open if magic[:2] == b"\x1f\x8b" else bz2.open if magic == b"BZh" else open
        with opener(path, "rb") as fh:
            head = fh.read(1 << 16).decode("latin-1")
    except (OSError, EOFError, ValueError, zlib.error):
        return False
    for line in head.split("\n")[:-1] or head.split("\n"):
        words = line.split()
        if words and not words[0].startswith("#"):
            return words[0] in KNOWN_NAMES
        if words and "message_name" in line:
            return True
    return False


def describe(path: str | Path) -> list[tuple[str, str]]:
    log = load(path)
    rows = [("messages", ", ".join(f"{k} {v}" for k, v in log.counts.most_common()))]
    for kind in SCAN_ORDER:
        if kind not in log.messages:
            continue
        m = log.messages[kind][0]
        n = len(m.ranges)
        last = math.degrees(m.start_angle + (n - 1) * m.angular_resolution)
        mr = max_range(log, kind)
        rows.append((f"laser {kind}", f"{n} beams, {math.degrees(m.start_angle):+.2f}..{last:+.2f} deg, "
                                      f"max range {mr if mr is not None else m.max_range:g} m, offset "
                                      f"{laser_offset(log, kind)}"))
        back = int((np.diff(_stamps(log.messages[kind])) < 0).sum())
        if back:
            rows.append((f"{kind} timestamps", f"{back} steps backwards (log order kept)"))
    return rows


def _write(traj: Trajectory, path: Path, options: ReadOptions) -> None:
    template = options.template
    if template is None and traj.meta.get("carmen_template") and Path(traj.meta["carmen_template"]).exists():
        template = traj.meta["carmen_template"]
    message = options.message or (traj.meta.get("carmen_message") if template is not None else None)
    if message not in (None,) + TRAJ_ORDER:
        message = None
    write_carmen(
        path, traj, template, message=message, overwrite_odometry=options.overwrite_odometry,
        force_planar=options.force_planar, options=options,
    )


trajectory_format(TrajectoryFormat(
    name="carmen",
    description="CARMEN log (FLASER / ROBOTLASER1 / ODOM poses; .clf, .log, .gz, .bz2)",
    read=read_carmen,
    write=_write,
    suffixes=SUFFIXES,
    sniff=sniff,
    describe=describe,
    ordered_stamps=False,  # log order is kept: real logs step back in time and repeat stamps
))

scan_source(ScanSource(
    name="carmen",
    description="CARMEN log 2D laser scans (FLASER / ROBOTLASER1 / RAWLASER), robot frame",
    open=open_carmen_scans,
    suffixes=SUFFIXES,
    sniff=sniff,
    describe=describe,
))
