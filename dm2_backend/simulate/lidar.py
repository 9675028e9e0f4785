"""Spinning multi-beam LiDAR (or a planar laser) ray-cast with open3d's RaycastingScene."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass
class LidarModel:
    """Beams spread evenly over the vertical field of view, ``columns`` azimuths over 360 degrees."""

    beams: int = 32
    fov_up_deg: float = 10.0
    fov_down_deg: float = -30.0
    columns: int = 720
    max_range: float = 80.0
    min_range: float = 0.5
    #: standard deviation of the range noise (m) and probability that a return is lost
    range_noise: float = 0.02
    dropout: float = 0.05
    #: planar mode: the laser sits this high above the pose (its points are then flattened to z = 0)
    height: float = 1.8
    planar: bool = False

    def check(self) -> None:
        if self.beams < 1 or self.columns < 1:
            raise ValueError("beams and columns must be positive")
        if not self.planar and self.fov_up_deg < self.fov_down_deg:
            raise ValueError("the upper field-of-view limit is below the lower one")
        if not 0 <= self.dropout < 1 or self.range_noise < 0 or not 0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= dropout < 1, range_noise >= 0 and 0 <= min_range < max_range")

    def directions(self) -> np.ndarray:
        """Unit ray directions (beams x columns, 3) in the sensor frame, beam-major."""
        az = np.linspace(-np.pi, np.pi, self.columns, endpoint=False)
        if self.planar:
            el = np.zeros(1)
        elif self.beams == 1:
            el = np.deg2rad([0.5 * (self.fov_down_deg + self.fov_up_deg)])
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
        return self.scan_with_intensity(pose, rng)[0]

    def scan_with_intensity(self, pose: np.ndarray, rng: np.random.Generator
                            ) -> tuple[np.ndarray, np.ndarray]:
        """Points (M,3) and intensities (M,) in [0, 1] (cosine of the incidence angle), float32."""
        m = self.model
        origin = pose[:3, 3] + (np.array([0, 0, m.height]) if m.planar else 0)
        d_world = self.dirs @ pose[:3, :3].T
        rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy()
        keep = np.isfinite(t) & (t < m.max_range) & (t > m.min_range)
        keep &= rng.uniform(size=len(t)) >= m.dropout
        r = t[keep] + rng.normal(0, m.range_noise, int(keep.sum()))
        cos = np.abs((hit["primitive_normals"].numpy()[keep] * d_world[keep]).sum(1))
        return (self.dirs[keep] * r[:, None]).astype(np.float32), cos.astype(np.float32)
