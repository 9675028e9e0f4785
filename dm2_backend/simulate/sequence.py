"""Simulate a whole sequence and write it in the KITTI-odometry layout a user's front end would give."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dm2_backend.formats.kitti import write_kitti
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.formats.scan_folder import write_bin
from dm2_backend.simulate.lidar import LidarModel, Raycaster
from dm2_backend.simulate.path import drifting_odometry, loop_path
from dm2_backend.simulate.scene import make_scene
from dm2_backend.trajectory import Trajectory


@dataclass
class SimSettings:
    frames: int = 300
    seed: int = 0
    extent: float = 40.0  # half size of the scene (m)
    laps: float = 2.0
    rate_hz: float = 10.0
    planar: bool = False
    lidar: LidarModel | None = None
    #: odometry drift per frame: yaw noise (rad), yaw bias (rad), translation noise (fraction of step)
    yaw_sigma: float = 0.003
    yaw_bias: float = 0.0015
    trans_sigma: float = 0.02


def simulate(s: SimSettings, progress: bool = True) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Scans (sensor frame), ground-truth poses and drifting odometry poses (N,4,4)."""
    lidar = s.lidar or LidarModel(planar=s.planar, columns=360 if s.planar else 720,
                                  max_range=0.9 * s.extent if s.planar else 2 * s.extent)
    caster = Raycaster(make_scene(s.extent, s.seed), lidar)
    gt = loop_path(s.frames, 0.7 * s.extent, s.laps, s.seed)
    rng = np.random.default_rng(s.seed)
    scans = [caster.scan(T, rng) for T in tqdm(gt, desc="simulate", disable=not progress, leave=False)]
    if s.planar:
        scans = [p * np.array([1, 1, 0], np.float32) for p in scans]
    warm = drifting_odometry(gt, s.seed + 1, s.yaw_sigma, s.trans_sigma, s.yaw_bias)
    return scans, gt, warm


def write_sequence(out: Path, scans: list[np.ndarray], gt: np.ndarray, warm: np.ndarray, rate_hz: float) -> None:
    """``velodyne/NNNNNN.bin``, ``poses.txt`` (ground truth, LiDAR frame), ``times.txt``, ``warm_start.txt``."""
    out = Path(out)
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    for i, p in enumerate(scans):
        write_bin(out / "velodyne" / f"{i:06d}.bin", p)
    times = np.arange(len(scans)) / rate_hz
    with open(out / "times.txt", "w") as fh:
        fh.writelines(f"{float(t)!r}\n" for t in times)
    write_kitti(Trajectory(gt, times), out / "poses.txt", ReadOptions())
    write_kitti(Trajectory(warm, times), out / "warm_start.txt", ReadOptions())
