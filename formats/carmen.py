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
* Readings ``<= min_range`` (0) or ``>= max_range`` are invalid and dropped, and so are isolated long returns
  (one beam far beyond two neighbours on one surface: glass, open doors; :mod:`dm2_backend.kernel.planar_returns`).
  ``max_range``: the ``ReadOptions.max_range``, else the message's ``maximum_range`` field, else (FLASER)
  CARMEN's 80 m, lowered to the log's largest reading when that value repeats as a saturation value (ACES: 50 m; a
  ROBOTLASER1 log whose field declares more than its scanner's 81.91 m code: 81.91 m).
* Log order is kept. Real logs have non-monotonic ipc timestamps (Intel: 631 steps back, up to 0.9 s, while
  the poses show file order is right) and duplicate ODOM stamps, so neither is an error here; the count of
  backward steps is in ``meta["unsorted_timestamps"]``.

Writing (:func:`write_carmen`): with a template log (``ReadOptions.template``, else the log the trajectory was
read from) only the pose fields of the matched laser messages change; without one, ODOM lines.
The Freiburg benchmark ``.relations`` files are read by :mod:`dm2_backend.formats.relations`.

``ReadOptions.topic`` picks the message kind (default FLASER, else ROBOTLASER1, else RAWLASER1/RAWLASER for
scans and ODOM for trajectories).
"""

from __future__ import annotations

import bz2
import gzip
import itertools
import math
import re
import zlib
from pathlib import Path

import numpy as np

from dm2_backend.formats.carmen_parser import (  # noqa: F401 (parse_line, Message, ...: the format's API)
    _TOKEN,
    CARMEN_MAX_RANGE,
    FRONT_KINDS,
    KNOWN_NAMES,
    POSE_KINDS,
    RAW_KINDS,
    SCAN_ORDER,
    SUFFIXES,
    TRAJ_ORDER,
    CarmenLog,
    Message,
    flaser_angles,
    load,
    parse_line,
    parse_log,
    read_text,
)
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.planar_returns import isolated_long_returns
from dm2_backend.kernel.scans import Scan, ScanSequence, SensorKind
from dm2_backend.kernel.trajectory import Trajectory, validate_poses
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError


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
    """The range at or beyond which readings are invalid; ``None``: the per-message maximum_range field.

    A scanner reports "no return" as a fixed code (a SICK LMS 81.91 m, ACES 50 m): the log's largest reading,
    repeated (at least 10 times and 1 in 1,000 readings), is that code and is dropped with everything beyond it,
    whatever the messages declare (a ``maximum_range`` field above the code would let the codes through as
    points: a ring around the robot that moves with it and pulls every scan match towards standing still).
    FLASER messages declare nothing: without a repeated code, CARMEN's 80 m."""
    if options is not None and options.max_range is not None:
        return float(options.max_range)
    msgs = [m for m in log.messages[kind] if m.ranges is not None and len(m.ranges)]
    code = saturation_code(msgs)
    if kind == "FLASER":
        return code if code is not None and code < CARMEN_MAX_RANGE else CARMEN_MAX_RANGE
    declared = [m.max_range for m in msgs if m.max_range is not None and m.max_range > 0]
    if code is not None and (len(declared) < len(msgs) or code < min(declared)):
        return code
    return None


def saturation_code(msgs: list[Message]) -> float | None:
    """The largest reading of ``msgs`` when it repeats as a saturation value (at least 10 times and 1 in 1,000
    readings), else None."""
    top = max((float(m.ranges.max()) for m in msgs), default=0.0)
    total = sum(len(m.ranges) for m in msgs)
    hits = sum(int((m.ranges == np.float32(top)).sum()) for m in msgs)
    return top if top > 0 and hits >= max(10, 1e-3 * total) else None


def scan_points(msg: Message, offset: tuple[float, float, float], max_r: float | None,
                min_r: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """Valid readings of ``msg`` as (M,3) float32 points in the robot frame, and their remissions; isolated long
    returns (:mod:`dm2_backend.kernel.planar_returns`) are not valid."""
    r = msg.ranges.astype(np.float64)
    limit = max_r if max_r is not None else msg.max_range
    valid = r > min_r
    if limit is not None and limit > 0:
        valid &= r < np.float32(limit)
    valid &= ~isolated_long_returns(r, valid, msg.angular_resolution)
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


def robotlaser1_line(ranges: np.ndarray, start_angle: float, resolution: float, max_range: float,
                     laser_pose, robot_pose, timestamp: float, host: str = "dm2", accuracy: float = 0.01) -> str:
    """One ``ROBOTLASER1`` message (laser type 0, no remissions, fov = (n - 1) x resolution; ranges ``%.2f``, the
    poses ``%.6f``; tv rv and the safety fields 0) as CARMEN's robot module writes it: the laser pose is the robot
    pose (+) the laser's mount."""
    r = np.asarray(ranges, dtype=np.float64)
    head = (f"ROBOTLASER1 0 {_fmt(start_angle)} {_fmt((len(r) - 1) * resolution)} {_fmt(resolution)} "
            f"{_fmt(max_range)} {_fmt(accuracy)} 0 {len(r)} " + " ".join(f"{v:.2f}" for v in r) + " 0")
    poses = " ".join(_fmt(float(v)) for v in (*laser_pose, *robot_pose))
    return f"{head} {poses} 0.000000 0.000000 0.000000 0.000000 0.000000 {float(timestamp)!r} {host} 0.000000"


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


# ---------------------------------------------------------------- detection, registration


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
    sensor=SensorKind.LASER_2D,
    open=open_carmen_scans,
    suffixes=SUFFIXES,
    sniff=sniff,
    describe=describe,
))
