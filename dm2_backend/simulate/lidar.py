"""Spinning multi-beam LiDAR (or a planar laser) ray-cast with open3d's RaycastingScene."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass
class LidarModel:
    beams: int = 32
    fov_up_deg: float = 10.0
    fov_down_deg: float = -30.0
    columns: int = 720
    max_range: float = 80.0
    range_noise: float = 0.02
    dropout: float = 0.05
    height: float = 1.8
    planar: bool = False

    def directions(self) -> np.ndarray:
        az = np.linspace(-np.pi, np.pi, self.columns, endpoint=False)
        if self.planar:
            el = np.zeros(1)
        else:
            el = np.deg2rad(np.linspace(self.fov_down_deg, self.fov_up_deg, self.beams))
        A, E = np.meshgrid(az, el)
        return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


class Raycaster:
    """Casts the LiDAR model's rays from a sensor pose into a mesh."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, model: LidarModel) -> None:
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self.model = model
        self.dirs = model.directions()

    def scan(self, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Points (M,3) float32 in the sensor frame for a sensor at ``pose`` (4x4, world)."""
        origin = pose[:3, 3] + (np.array([0, 0, self.model.height]) if self.model.planar else 0)
        d_world = self.dirs @ pose[:3, :3].T
        rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1).astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        keep = np.isfinite(t) & (t < self.model.max_range) & (rng.uniform(size=len(t)) >= self.model.dropout)
        r = t[keep] + rng.normal(0, self.model.range_noise, keep.sum())
        return (self.dirs[keep] * r[:, None]).astype(np.float32)
