"""Simulate a whole sequence and write it in the KITTI-odometry layout a user's front end would give."""

from __future__ import annotations

import json
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from evo.core.geometry import umeyama_alignment

from dm2_backend import __version__
from dm2_backend.formats.kitti import write_kitti
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.formats.scan_folder import write_bin
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.simulate.lidar import LidarModel, Raycaster
from dm2_backend.simulate.path import centerline, drifting_odometry, street_path
from dm2_backend.simulate.scene import make_scene


@dataclass
class SimSettings:
    frames: int = 300
    seed: int = 0
    extent: float = 40.0  # half size of the scene (m); the street's radius is 0.7 x extent
    laps: float = 2.0
    path: str = "loop"  # "loop" or "eight"
    rate_hz: float = 10.0
    planar: bool = False
    #: None: 32 beams x 720 columns, range min(2 x extent, 100 m) (3D); 360 columns at 0.5 m height (planar)
    lidar: LidarModel | None = None
    #: odometry drift (random walk): yaw bias (rad per metre driven), yaw noise (rad per sqrt(metre)),
    #: translation noise (fraction of each step), and in 3D z noise (fraction) and roll/pitch (rad / sqrt(m))
    yaw_bias: float = 0.00035  # 2 degrees per 100 m
    yaw_sigma: float = 0.001
    trans_sigma: float = 0.02
    z_sigma: float = 0.01
    tilt_sigma: float = 0.0003

    def lidar_model(self) -> LidarModel:
        if self.lidar is not None:
            return self.lidar
        if self.planar:
            return LidarModel(planar=True, columns=360, max_range=min(0.9 * self.extent, 40.0), height=0.5)
        return LidarModel(max_range=min(2.0 * self.extent, 100.0))


class Simulation:
    """The scene, the ground-truth LiDAR poses, the drifting odometry and scans on demand (any order)."""

    def __init__(self, s: SimSettings) -> None:
        if s.frames < 2:
            raise ValueError("simulate at least 2 frames")
        self.settings = s
        self.lidar = s.lidar_model()
        self.lidar.check()
        if self.lidar.planar != s.planar:
            raise ValueError("the LiDAR model's planar flag differs from the settings'")
        radius = 0.7 * s.extent
        self.mesh = make_scene(s.extent, s.seed, centerline(s.path, radius, s.seed))
        self.caster = Raycaster(self.mesh, self.lidar)
        self.gt = street_path(s.path, s.frames, radius, s.laps, s.seed)
        if not s.planar:
            self.gt[:, 2, 3] = self.lidar.height  # the LiDAR frame sits on the vehicle's roof
        step = float(np.median(np.linalg.norm(np.diff(self.gt[:, :3, 3], axis=0), axis=1)))
        self.warm = drifting_odometry(
            self.gt, s.seed + 1, yaw_sigma=s.yaw_sigma * np.sqrt(step), trans_sigma=s.trans_sigma,
            yaw_bias=s.yaw_bias * step, z_sigma=0.0 if s.planar else s.z_sigma,
            tilt_sigma=0.0 if s.planar else s.tilt_sigma * np.sqrt(step),
        )
        self.times = np.arange(s.frames) / s.rate_hz

    def __len__(self) -> int:
        return len(self.gt)

    def scan(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Points (sensor frame; z = 0 in planar mode) and intensities of frame ``i``."""
        rng = np.random.default_rng([self.settings.seed, 1, i])
        points, intensity = self.caster.scan_with_intensity(self.gt[i], rng)
        if self.settings.planar:
            points[:, 2] = 0.0
        return points, intensity


def simulate(s: SimSettings, progress: bool = True) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Scans (sensor frame), ground-truth poses and drifting odometry poses (N,4,4), in memory."""
    sim = Simulation(s)
    frames = progress_of(range(len(sim)), "simulate", unit="frame", enabled=progress)
    scans = [sim.scan(i)[0] for i in frames]
    return scans, sim.gt, sim.warm


def write_sequence(out: Path, scans: list[np.ndarray], gt: np.ndarray, warm: np.ndarray,
                   rate_hz: float) -> None:
    """``velodyne/NNNNNN.bin``, ``poses.txt`` (ground truth, LiDAR frame), ``times.txt``,
    ``warm_start.txt``."""
    out = Path(out)
    for i, p in enumerate(scans):  # (each write makes its folder)
        write_bin(out / "velodyne" / f"{i:06d}.bin", p)
    _write_trajectories(out, gt, warm, np.arange(len(scans)) / rate_hz)


def _write_trajectories(out: Path, gt: np.ndarray, warm: np.ndarray, times: np.ndarray) -> None:
    with atomic_write(out / "times.txt") as fh:
        fh.writelines(f"{float(t)!r}\n" for t in times)
    write_kitti(Trajectory(gt, times), out / "poses.txt", ReadOptions())
    write_kitti(Trajectory(warm, times), out / "warm_start.txt", ReadOptions())


def generate(s: SimSettings, out: Path, progress: bool = True) -> dict:
    """Simulate straight to disk (scans are not kept in memory; files are written by a second thread
    while the next frame is ray-cast) and label the folder: ``info.json`` and ``README.txt``."""
    out = Path(out)
    t0 = time.perf_counter()
    sim = Simulation(s)
    counts = np.zeros(len(sim), dtype=np.int64)
    pending: deque[Future] = deque()
    with ThreadPoolExecutor(max_workers=1) as pool:
        for i in progress_of(range(len(sim)), "simulate", unit="frame", enabled=progress):
            points, intensity = sim.scan(i)
            counts[i] = len(points)
            pending.append(pool.submit(write_bin, out / "velodyne" / f"{i:06d}.bin", points, intensity))
            while len(pending) > 8 or (pending and pending[0].done()):
                pending.popleft().result()
        for f in pending:
            f.result()
    _write_trajectories(out, sim.gt, sim.warm, sim.times)
    info = describe(sim, counts, time.perf_counter() - t0)
    with atomic_write(out / "info.json") as fh:
        json.dump(info, fh, indent=2)
    with atomic_write(out / "README.txt") as fh:
        fh.write(readme_text(info))
    return info


def _ate(gt: np.ndarray, est: np.ndarray) -> float:
    """Translation ATE RMSE (m) after SE(3) alignment."""
    R, t, _ = umeyama_alignment(est[:, :3, 3].T, gt[:, :3, 3].T, with_scale=False)
    d = est[:, :3, 3] @ R.T + t - gt[:, :3, 3]
    return float(np.sqrt((d * d).sum(1).mean()))


def describe(sim: Simulation, counts: np.ndarray, seconds: float) -> dict:
    s = sim.settings
    settings = asdict(s)
    settings["lidar"] = asdict(sim.lidar)
    drift = np.linalg.norm(sim.warm[:, :3, 3] - sim.gt[:, :3, 3], axis=1)
    return {
        "simulated": True,
        "generator": f"dm2 simulate (dm2 {__version__})",
        "settings": settings,
        "frames": len(sim),
        "points_per_frame": {"mean": float(counts.mean()), "min": int(counts.min()),
                             "max": int(counts.max())},
        "path_length_m": float(np.linalg.norm(np.diff(sim.gt[:, :3, 3], axis=0), axis=1).sum()),
        "warm_start": {"ate_rmse_m": _ate(sim.gt, sim.warm), "final_position_error_m": float(drift[-1]),
                       "max_position_error_m": float(drift.max())},
        "seconds": round(seconds, 3),
    }


def readme_text(info: dict) -> str:
    s = info["settings"]
    lidar = s["lidar"]
    kind = "planar 2D laser" if s["planar"] else f"{lidar['beams']}-beam spinning LiDAR"
    return f"""SIMULATED DATA - not recorded by a real sensor.

Generated by {info['generator']}: a {kind} ({lidar['columns']} columns, range {lidar['max_range']:g} m,
range noise {lidar['range_noise']:g} m, dropout {lidar['dropout']:g}) ray-cast with open3d against a
procedural scene (ground, buildings, walls, poles, parked cars; seed {s['seed']}), along {s['laps']:g} laps
of a {s['path']} path ({info['path_length_m']:.0f} m, {info['frames']} frames at {s['rate_hz']:g} Hz).

velodyne/NNNNNN.bin  scans, float32 x y z intensity (sensor frame{'; z = 0' if s['planar'] else ''})
times.txt            one timestamp (s) per scan
poses.txt            ground truth, KITTI format (LiDAR frame, no calib needed)
warm_start.txt       drifting odometry (random walk in yaw and translation), KITTI format:
                     ATE {info['warm_start']['ate_rmse_m']:.2f} m against poses.txt
info.json            every setting used

Refine it:  dm2 refine --scans velodyne --poses warm_start.txt --gt poses.txt --out run
"""
