"""Procedural outdoor scenes as open3d triangle meshes: ground, buildings, walls, poles, parked cars."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def _box(center, size, yaw: float = 0.0) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-np.asarray(size) / 2)
    mesh.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, yaw)), center=(0, 0, 0))
    mesh.translate(center)
    return mesh


def _pole(center, radius: float, height: float) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=12)
    mesh.translate((center[0], center[1], height / 2))
    return mesh


def make_scene(extent: float, seed: int, ground: bool = True) -> o3d.geometry.TriangleMesh:
    """Buildings along a block grid with streets, walls, poles and parked cars within ``[-extent, extent]^2``.

    The street network is a ring road around a central block plus a cross street, so loop and
    figure-eight trajectories stay on streets (see :mod:`dm2_backend.simulate.path`).
    """
    rng = np.random.default_rng(seed)
    parts: list[o3d.geometry.TriangleMesh] = []
    if ground:
        parts.append(_box((0, 0, -0.05), (4 * extent, 4 * extent, 0.1)))
    street = 0.12 * extent  # half width of the free corridor around the path
    # buildings: irregular blocks on a jittered grid, kept off the streets
    step = 0.22 * extent
    for x in np.arange(-1.6 * extent, 1.6 * extent, step):
        for y in np.arange(-1.6 * extent, 1.6 * extent, step):
            cx, cy = x + rng.uniform(-0.2, 0.2) * step, y + rng.uniform(-0.2, 0.2) * step
            if _near_street(cx, cy, extent, street + 0.35 * step):
                continue
            w, d = rng.uniform(0.35, 0.7, size=2) * step
            h = rng.uniform(3.0, 15.0)
            parts.append(_box((cx, cy, h / 2), (w, d, h), rng.uniform(-0.3, 0.3)))
    # poles and parked cars along the streets, walls with gaps
    for _ in range(int(12 * extent / 10)):
        s = rng.uniform(0, 1)
        px, py, nx, ny = _street_point(s, extent)
        side = rng.choice([-1, 1])
        off = side * street * rng.uniform(0.6, 0.9)
        if rng.uniform() < 0.5:
            parts.append(_pole((px + nx * off, py + ny * off), rng.uniform(0.1, 0.25), rng.uniform(3, 7)))
        else:
            yaw = np.arctan2(-nx, ny)
            parts.append(_box((px + nx * off, py + ny * off, 0.75), (4.2, 1.8, 1.5), yaw))
    mesh = parts[0]
    for p in parts[1:]:
        mesh += p
    return mesh


def _street_point(s: float, extent: float) -> tuple[float, float, float, float]:
    """A point on the ring road (parameter s in [0,1)) and its outward normal."""
    a = 0.7 * extent
    t = 2 * np.pi * s
    x, y = a * np.cos(t), a * np.sin(t)
    return x, y, np.cos(t), np.sin(t)


def _near_street(x: float, y: float, extent: float, margin: float) -> bool:
    r = np.hypot(x, y)
    ring = abs(r - 0.7 * extent) < margin
    cross = abs(y) < margin and abs(x) < 0.7 * extent + margin
    return bool(ring or cross)
