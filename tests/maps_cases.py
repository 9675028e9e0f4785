"""A simulated room for the map tests: four walls and a pillar (and a floor and ceiling in 3D), scanned with the
project's LiDAR simulator from a few poses inside, the exact distance to its surfaces, and a small M-Net trained
directly on the scans (the maps' geometry is tested, not the optimiser)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d
import torch

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.optim.losses import occupancy_bce
from dm2_backend.optim.occupancy import GridOccupancy
from dm2_backend.simulate.lidar import LidarModel, Raycaster

HALF = (5.0, 3.0)  # interior half sizes (m) in x and y
PILLAR = (2.0, 1.0, 0.3)  # centre x, y and half size of a square pillar
HEIGHT = 3.0  # floor z = 0, ceiling z = HEIGHT (3D)
XY_YAW = [(-3.5, -1.5, 0.3), (-3.5, 1.5, -0.5), (-1.0, 0.0, 1.0), (1.0, -2.0, 2.0), (3.5, -1.5, 2.5),
          (3.5, 2.0, -2.5), (0.0, 2.0, -1.0), (-2.0, -2.0, 0.0)]


def _box(center, size) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(np.asarray(center, float) - np.asarray(size, float) / 2)
    return m


def room_mesh(floor: bool) -> o3d.geometry.TriangleMesh:
    (hx, hy), t, h = HALF, 0.2, HEIGHT
    parts = [_box((0, s * (hy + t / 2), h / 2), (2 * hx + 2 * t, t, h)) for s in (-1, 1)]
    parts += [_box((s * (hx + t / 2), 0, h / 2), (t, 2 * hy, h)) for s in (-1, 1)]
    parts.append(_box((PILLAR[0], PILLAR[1], h / 2), (2 * PILLAR[2], 2 * PILLAR[2], h)))
    if floor:
        parts += [_box((0, 0, -t / 2), (2 * hx + 2 * t, 2 * hy + 2 * t, t)),
                  _box((0, 0, h + t / 2), (2 * hx + 2 * t, 2 * hy + 2 * t, t))]
    mesh = parts[0]
    for p in parts[1:]:
        mesh += p
    return mesh


def distance(points: np.ndarray, planar: bool) -> np.ndarray:
    """Distance (m) of points inside the room to its nearest surface."""
    p = np.asarray(points, float)
    d = np.minimum(HALF[0] - np.abs(p[:, 0]), HALF[1] - np.abs(p[:, 1]))
    dx = np.maximum(np.abs(p[:, 0] - PILLAR[0]) - PILLAR[2], 0)
    dy = np.maximum(np.abs(p[:, 1] - PILLAR[1]) - PILLAR[2], 0)
    d = np.minimum(np.abs(d), np.hypot(dx, dy))
    if not planar:
        d = np.minimum(d, np.minimum(np.abs(p[:, 2]), np.abs(HEIGHT - p[:, 2])))
    return d


def wall_samples(step: float = 0.05) -> np.ndarray:
    """Points (K, 2) on the interior faces of the walls and the pillar."""
    (hx, hy), (px, py, r) = HALF, PILLAR
    xs, ys = np.arange(-hx, hx, step) + step / 2, np.arange(-hy, hy, step) + step / 2
    out = [np.column_stack([xs, np.full_like(xs, s * hy)]) for s in (-1, 1)]
    out += [np.column_stack([np.full_like(ys, s * hx), ys]) for s in (-1, 1)]
    ps = np.arange(-r, r, step) + step / 2
    out += [np.column_stack([px + ps, np.full_like(ps, py + s * r)]) for s in (-1, 1)]
    out += [np.column_stack([np.full_like(ps, px + s * r), py + ps]) for s in (-1, 1)]
    return np.concatenate(out)


@dataclass
class Room:
    planar: bool
    poses: np.ndarray  # (N, 4, 4) sensor poses
    scans: list[np.ndarray]  # sensor frame

    def sequence(self) -> ScanSequence:
        return ScanSequence(loader=lambda i: Scan(self.scans[i]), count=len(self.scans),
                            timestamps=np.arange(len(self.scans)) * 0.1, planar=self.planar, source="room")

    def world(self) -> list[np.ndarray]:
        return [p @ T[:3, :3].T + T[:3, 3] for p, T in zip(self.scans, self.poses)]


@lru_cache(maxsize=2)
def room(planar: bool) -> Room:
    if planar:
        model = LidarModel(planar=True, beams=1, columns=360, max_range=20.0, min_range=0.05, range_noise=0.005,
                           dropout=0.0, height=0.5)
    else:
        model = LidarModel(beams=24, fov_up_deg=70.0, fov_down_deg=-70.0, columns=180, max_range=20.0,
                           min_range=0.1, range_noise=0.005, dropout=0.0)
    poses = se3.from_xy_yaw(np.array(XY_YAW))
    if not planar:
        poses[:, 2, 3] = 1.5
    caster = Raycaster(room_mesh(floor=not planar), model)
    scans = []
    for i, T in enumerate(poses):
        pts = caster.scan(T, np.random.default_rng(i))
        if planar:
            pts[:, 2] = 0.0
        scans.append(pts)
    return Room(planar, poses, scans)


def train_field(r: Room, world_from_field: np.ndarray, cell: float, steps: int, seed: int = 0, batch: int = 1024,
                levels: int = 6, max_cells: int = 2**16, lr: float = 2e-2) -> GridOccupancy:
    """An occupancy field trained with the optimiser's BCE on the room's scans, in a frame that differs from the
    world by ``world_from_field``: hits are occupied, points along each beam up to one cell short are free."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    inv = np.linalg.inv(world_from_field)
    hits = np.concatenate(r.world()) @ inv[:3, :3].T + inv[:3, 3]
    origins = np.repeat(r.poses[:, :3, 3] @ inv[:3, :3].T + inv[:3, 3], [len(s) for s in r.scans], axis=0)
    dim = 2 if r.planar else 3
    lo, hi = hits.min(0)[:dim] - 1.0, hits.max(0)[:dim] + 1.0
    field = GridOccupancy(lo, hi, cell, levels=levels, max_cells=max_cells)
    opt = torch.optim.Adam(field.parameters(), lr=lr)
    for _ in range(steps):
        k = rng.choice(len(hits), batch)
        ray = hits[k] - origins[k]
        length = np.linalg.norm(ray, axis=1, keepdims=True)
        u = rng.uniform(0, 1, (len(k), 4, 1)) * np.clip(1 - cell / length, 0, 1)[:, None]
        free = origins[k][:, None] + u * ray[:, None]
        loss = occupancy_bce(field, torch.from_numpy(hits[k]).float(), torch.from_numpy(free).float())
        opt.zero_grad()
        loss.backward()
        opt.step()
    return field
