"""A CARMEN log like the Freiburg hospital's (issue 27): ROBOTLASER1 messages only, a laser mounted ahead of the
axle, interlaced quarter scans, max-range codes and isolated long returns, pauses in the log, drifting wheel
odometry, in a ring of long corridors (:mod:`dm2_backend.simulate.corridor`).

Each trait can be switched off alone (:class:`HospitalTraits`), so that the cause of a failure can be found
trait by trait; :func:`write_hospital` writes the log, the true robot poses (TUM) and Freiburg relations.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import open3d as o3d

from dm2_backend.formats.carmen import robotlaser1_line
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.formats.tum import write_tum
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.simulate.corridor import _boxes, corridor_walls, ring_path
from dm2_backend.simulate.path import drifting_odometry

#: the SICK LMS's "no return" code (m): 8191 cm
MAX_RANGE_CODE = 81.91


@dataclass(frozen=True)
class HospitalTraits:
    """What makes the log hard; :meth:`plain` switches all of them off (a clean log of the same run)."""

    #: the laser's mount ahead of the robot's axle (m)
    laser_offset: float = 0.22
    #: a 0.25 deg scanner delivering its sweep in four interlaced quarters of 1 deg beams
    interlaced: bool = True
    #: share of beams returned as the max-range code (glass, black surfaces, open space)
    code_share: float = 0.08
    #: share of beams with a near return (< 10 m) replaced by an isolated long return of 30-50 m
    long_share: float = 0.04
    #: pauses of the log: (count, shortest, longest) in seconds; the robot moves one step across each
    gaps: tuple[int, float, float] = (15, 5.0, 198.0)
    #: the maximum_range field the messages declare (m); above the code, the codes are readings to a reader
    #: that trusts the field
    declared_max_range: float = 100.0

    def plain(self) -> HospitalTraits:
        return replace(self, laser_offset=0.0, interlaced=False, code_share=0.0, long_share=0.0, gaps=(0, 0.0, 0.0),
                       declared_max_range=MAX_RANGE_CODE)


@dataclass(frozen=True)
class HospitalSettings:
    frames: int = 600
    seed: int = 0
    #: the ring's centre line (m) and the corridors' width: long wide corridors (halls) whose median range (13 m)
    #: is near the hospital's 10.5 m
    length: float = 80.0
    width: float = 40.0
    corridor: float = 16.0
    #: metres per scan and the median scan rate (Hz)
    step: float = 0.2
    rate_hz: float = 1.6
    range_noise: float = 0.01
    #: wheel odometry: scale error (fraction of each step), yaw bias (rad per metre), yaw noise (rad per
    #: square-root metre), translation noise (fraction of each step)
    scale_error: float = 0.005
    yaw_bias: float = 0.0005
    yaw_noise: float = 0.0005
    trans_noise: float = 0.005
    traits: HospitalTraits = HospitalTraits()


@dataclass
class HospitalLog:
    """The simulated log in memory: one ROBOTLASER1 line per scan, the true and odometry robot poses and stamps."""

    lines: list[str]
    truth: np.ndarray
    odometry: np.ndarray
    stamps: np.ndarray
    settings: HospitalSettings


def beam_angles(k: int, interlaced: bool) -> tuple[float, np.ndarray]:
    """Start angle and beam angles (rad) of message ``k``: 1 deg beams, starting at -90, -89.75, -89.5 or -89.25 deg
    in turn when interlaced (181 beams from -90, else 180), 181 beams from -90 deg otherwise."""
    quarter = k % 4 if interlaced else 0
    start = math.radians(-90.0 + 0.25 * quarter)
    n = 181 if quarter == 0 else 180
    return start, start + np.radians(1.0) * np.arange(n)


def pauses(n: int, gaps: tuple[int, float, float], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Where the log pauses and for how long: indices ``i`` of the intervals (scan ``i`` to ``i + 1``, never the
    first or last) and their lengths (s); none when ``gaps`` counts none or the log is too short for them."""
    count, lo, hi = gaps
    if not count or n <= 2 * count + 2:
        return np.zeros(0, int), np.zeros(0)
    at = rng.choice(np.arange(1, n - 1), size=count, replace=False)
    return at, rng.uniform(lo, hi, count)


def returns_with_traits(r: np.ndarray, t: HospitalTraits, rng: np.random.Generator) -> np.ndarray:
    """A scan's ranges (m) as the hospital's scanner writes them: no return (not finite, or at least the code) as
    the max-range code, a ``long_share`` of the near returns (< 10 m) as isolated long returns of 30-50 m, and a
    ``code_share`` of all beams as the code; ``r`` is changed in place and returned."""
    r[~np.isfinite(r) | (r >= MAX_RANGE_CODE)] = MAX_RANGE_CODE
    near = r < 10.0
    long = near & (rng.uniform(size=len(r)) < t.long_share)
    r[long] = rng.uniform(30.0, 50.0, int(long.sum()))
    r[rng.uniform(size=len(r)) < t.code_share] = MAX_RANGE_CODE
    return r


def _stamps(n: int, rate_hz: float, gaps: tuple[int, float, float], rng: np.random.Generator) -> np.ndarray:
    dt = rng.uniform(0.8, 1.2, n - 1) / rate_hz
    at, length = pauses(n, gaps, rng)
    dt[at] = length
    return 1_000_000_000.0 + np.concatenate([[0.0], np.cumsum(dt)])


def simulate_hospital(s: HospitalSettings) -> HospitalLog:
    """Ray-cast the ring with the laser at ``truth (+) mount`` and write its messages with the odometry's poses."""
    t = s.traits
    lap = 2.0 * (s.length + s.width)
    truth = ring_path(s.length, s.width, s.step, laps=1.02 * s.frames * s.step / lap)[: s.frames]
    if len(truth) < s.frames:
        raise ValueError("the ring path is shorter than the frames asked for")
    rng = np.random.default_rng([s.seed, 27])
    odometry = drifting_odometry(truth, s.seed + 1, yaw_sigma=s.yaw_noise * math.sqrt(s.step),
                                 trans_sigma=s.trans_noise, yaw_bias=s.yaw_bias * s.step, scale_error=s.scale_error)
    odometry = odometry @ se3.inverse(odometry[0]) @ truth[0]  # both start at the first true pose
    mount = se3.from_xy_yaw(np.array([t.laser_offset, 0.0, 0.0]))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(
        _boxes(corridor_walls(s.length, s.width, s.corridor, doors=5))))
    stamps = _stamps(s.frames, s.rate_hz, t.gaps, rng)
    lines = []
    for k in range(s.frames):
        laser = truth[k] @ mount
        start, angles = beam_angles(k, t.interlaced)
        yaw = se3.to_xy_yaw(laser)[2] + angles
        rays = np.zeros((len(angles), 6), np.float32)
        rays[:, :2] = laser[:2, 3]
        rays[:, 2] = 1.0
        rays[:, 3], rays[:, 4] = np.cos(yaw), np.sin(yaw)
        r = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        r = r + rng.normal(0.0, s.range_noise, len(r))
        r = returns_with_traits(r, t, rng)
        robot = se3.to_xy_yaw(odometry[k])
        lines.append(robotlaser1_line(r, start, math.radians(1.0), t.declared_max_range,
                                      se3.to_xy_yaw(odometry[k] @ mount), robot, stamps[k], host="hospital-sim"))
    return HospitalLog(lines, truth, odometry, stamps, s)


def relations(log: HospitalLog, spans: tuple[int, ...] = (1, 5, 25, 100), every: int = 3) -> np.ndarray:
    """Freiburg relations ``t1 t2 x y z roll pitch yaw`` from the true poses: every ``every``-th scan to the
    scans ``spans`` later (0.2 to 20 m apart at the default step)."""
    rows = []
    for span in spans:
        i = np.arange(0, len(log.truth) - span, every)
        rel = se3.to_xy_yaw(se3.relative(log.truth[i], log.truth[i + span]))
        rows.append(np.column_stack([log.stamps[i], log.stamps[i + span], rel[:, 0], rel[:, 1],
                                     np.zeros((len(i), 3)), rel[:, 2]]))
    return np.concatenate(rows)


def write_hospital(out: Path, s: HospitalSettings) -> dict:
    """``hospital.clf`` (the log), ``truth.tum`` (true robot poses), ``hospital.relations`` and ``info.json``
    into ``out``; returns the info."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = simulate_hospital(s)
    with atomic_write(out / "hospital.clf") as fh:
        fh.write("# SIMULATED hospital-like log (dm2 simulate --scene hospital)\n")
        fh.write("\n".join(log.lines) + "\n")
    write_tum(Trajectory(log.truth, log.stamps, planar=True), out / "truth.tum", ReadOptions())
    rel = relations(log)
    with atomic_write(out / "hospital.relations") as fh:
        fh.writelines(" ".join(f"{v:.6f}" for v in row) + "\n" for row in rel)
    err = np.linalg.norm(log.odometry[:, :2, 3] - log.truth[:, :2, 3], axis=1)
    info = {"simulated": True, "settings": asdict(s), "frames": s.frames,
            "path_length_m": float(s.step * (s.frames - 1)),
            "odometry": {"max_position_error_m": float(err.max()), "final_position_error_m": float(err[-1])}}
    with atomic_write(out / "info.json") as fh:
        json.dump(info, fh, indent=2)
    return info
