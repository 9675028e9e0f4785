"""A small simulated planar sequence shared by the optimiser tests (built once per test session):
scans, ground truth, drifting warm start, frames, radius topology and pairwise registrations."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import yaml

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.plugins.registration_icp import IcpRegistration
from dm2_backend.plugins.topology_radius import RadiusTopology
from dm2_backend.prepare.frames import load_frames
from dm2_backend.simulate.sequence import SimSettings, simulate, write_sequence

FRAMES = 60
#: 2 laps of a 14 m-radius street (about 3 m between frames, so neighbours overlap and the laps close loops)
EXTENT = 20.0


@dataclass
class Case:
    scans: list[np.ndarray]
    gt: np.ndarray
    warm: np.ndarray
    frames: Frames
    topology: Topology  # radius search on the warm start
    pairwise: Pairwise  # the ``icp`` registration plugin on that topology

    def pairwise_from(self, poses: np.ndarray, topology: Topology | None = None) -> Pairwise:
        """Exact relatives inv(T_i) @ T_j of ``poses`` for each pair of ``topology`` (default: the case's)."""
        groups = (topology or self.topology).groups
        n, k = groups.shape
        rel = np.tile(np.eye(4), (n, k, 1, 1))
        valid = groups >= 0
        rows, cols = np.nonzero(valid)
        rel[rows, cols] = se3.relative(poses[rows], poses[groups[rows, cols]])
        return Pairwise(rel, valid, valid.astype(float), np.zeros((n, k)))


def frames_of(scans: list[np.ndarray], planar: bool = True, max_points: int = 256) -> Frames:
    seq = ScanSequence(loader=lambda i: Scan(scans[i]), count=len(scans),
                       timestamps=np.arange(len(scans)) * 0.1, planar=planar, source="simulated")
    return load_frames(seq, max_points, progress=False)


@lru_cache(maxsize=2)
def planar_case(frames: int = FRAMES, seed: int = 0) -> Case:
    settings = SimSettings(frames=frames, seed=seed, planar=True, extent=EXTENT)
    scans, gt, warm = simulate(settings, progress=False)
    fr = frames_of(scans)
    topo = RadiusTopology().run(fr, warm)
    pair = IcpRegistration(progress=False).run(fr, warm, topo)
    return Case(scans, gt, warm, fr, topo, pair)


def write_planar_sequence(root: Path, config: dict) -> Path:
    """The planar case written as the CLI tests read it (``velodyne/``, ``poses.txt`` ground truth, ``times.txt``,
    ``warm_start.txt``) with ``config`` as ``config.yaml``."""
    case = planar_case()
    write_sequence(root, case.scans, case.gt, case.warm, 10.0)
    (root / "config.yaml").write_text(yaml.safe_dump(config))
    return root


def small_config(**kw) -> OptimConfig:
    """A fast optimiser configuration for tests (few points, a small occupancy grid)."""
    base = dict(epochs=4, points_per_frame=64, bce_points_per_frame=32, batch_groups=16, grid_max_cells=2**14)
    return OptimConfig(**{**base, **kw})


def perturb(poses: np.ndarray, sigma_t: float, sigma_yaw: float, seed: int = 0) -> np.ndarray:
    """Planar poses with independent random x, y, yaw errors on every frame but the first."""
    rng = np.random.default_rng(seed)
    noise = np.column_stack([rng.normal(0, sigma_t, (len(poses), 2)), rng.normal(0, sigma_yaw, len(poses))])
    noise[0] = 0
    return poses @ se3.from_xy_yaw(noise)


def one_thread():
    """Fixture body: torch's intra-op threads only add overhead on these tiny tensors (and stall badly on a
    loaded 2-core machine), so the optimiser tests run single-threaded."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
