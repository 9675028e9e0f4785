"""Procedural outdoor scenes as open3d triangle meshes: ground, buildings, walls, poles, parked cars.

The scene is built around the street the vehicle drives (a closed centre line from
:func:`dm2_backend.simulate.path.centerline`): a free corridor along it, parked cars, poles and garden
walls at its sides, and blocks of buildings of varied footprint and height behind them.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree


def _box(center, size, yaw: float = 0.0) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-np.asarray(size, dtype=float) / 2)
    mesh.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, yaw)), center=(0, 0, 0))
    mesh.translate(center)
    return mesh


def _pole(center, radius: float, height: float) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=12)
    mesh.translate((center[0], center[1], height / 2))
    return mesh


def _car(x: float, y: float, yaw: float, rng: np.random.Generator) -> list[o3d.geometry.TriangleMesh]:
    """A body and a cabin (4.0-4.8 m long)."""
    length, width = rng.uniform(4.0, 4.8), rng.uniform(1.7, 1.9)
    c, s = np.cos(yaw), np.sin(yaw)
    shift = rng.uniform(-0.4, 0.1) * length / 2  # cabin a little towards the back
    return [
        _box((x, y, 0.25 + 0.4), (length, width, 0.8), yaw),
        _box((x + c * shift, y + s * shift, 1.05 + 0.3), (0.5 * length, 0.9 * width, 0.6), yaw),
    ]


def street_width(extent: float) -> float:
    """Half width of the free corridor along the centre line (m)."""
    return float(np.clip(0.12 * extent, 4.0, 8.0))


class _Street:
    """Nearest-distance queries against the centre line and points beside it."""

    def __init__(self, line: np.ndarray) -> None:
        self.line = line
        self.tree = cKDTree(line)
        seg = np.linalg.norm(np.diff(np.vstack([line, line[:1]]), axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.roll(line, -1, axis=0) - np.roll(line, 1, axis=0)
        self.tangent = t / np.linalg.norm(t, axis=1, keepdims=True)

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def distance(self, xy: np.ndarray) -> np.ndarray:
        return self.tree.query(np.atleast_2d(xy))[0]

    def beside(self, u: float, offset: float) -> tuple[np.ndarray, float]:
        """Point ``offset`` m left (+) / right (-) of arc length ``u``, and the street's heading there."""
        i = int(np.searchsorted(self.arc, u % self.length, side="right") - 1) % len(self.line)
        tx, ty = self.tangent[i]
        return self.line[i] + offset * np.array([-ty, tx]), float(np.arctan2(ty, tx))


def make_scene(extent: float, seed: int, line: np.ndarray, ground: bool = True) -> o3d.geometry.TriangleMesh:
    """Ground, buildings, walls, poles and parked cars within about ``[-1.6 extent, 1.6 extent]^2`` around
    the street centre line ``line`` (K,2) (kept free: nothing closer than half the street width)."""
    rng = np.random.default_rng([seed, 11])
    street = _Street(line)
    width = street_width(extent)
    parts: list[o3d.geometry.TriangleMesh] = []
    if ground:
        parts.append(_box((0, 0, -0.05), (4 * extent, 4 * extent, 0.1)))

    def clear(points: np.ndarray, margin: float) -> bool:
        return bool((street.distance(points) >= margin).all())

    # buildings: irregular blocks on a jittered grid, behind the street's sides
    step = float(np.clip(0.22 * extent, 6.0, 25.0))
    for x in np.arange(-1.6 * extent, 1.6 * extent, step):
        for y in np.arange(-1.6 * extent, 1.6 * extent, step):
            cx, cy = x + rng.uniform(-0.2, 0.2) * step, y + rng.uniform(-0.2, 0.2) * step
            w, d = rng.uniform(0.35, 0.75, size=2) * step
            h = rng.uniform(3.0, 18.0)
            yaw = rng.uniform(-0.4, 0.4)
            if rng.uniform() < 0.12 or not clear(np.array([cx, cy]), width + 1.0 + 0.5 * np.hypot(w, d)):
                continue  # an empty lot, or too close to the street
            parts.append(_box((cx, cy, h / 2), (w, d, h), yaw))
    # street furniture at both sides, spaced along the street
    u = 0.0
    while u < street.length:
        u += rng.exponential(4.0)
        side = rng.choice([-1.0, 1.0])
        kind = rng.choice(["car", "pole", "wall"], p=[0.45, 0.35, 0.2])
        if kind == "car":
            (x, y), yaw = street.beside(u, side * width * rng.uniform(0.6, 0.8))
            if clear(np.array([[x, y]]), 0.55 * width):
                parts += _car(x, y, yaw + rng.normal(0, 0.05), rng)
        elif kind == "pole":
            (x, y), _ = street.beside(u, side * width * rng.uniform(0.85, 0.95))
            if clear(np.array([[x, y]]), 0.8 * width):
                parts.append(_pole((x, y), rng.uniform(0.08, 0.25), rng.uniform(3.0, 8.0)))
        else:
            length = rng.uniform(5.0, 15.0)
            (x, y), yaw = street.beside(u, side * width * 0.97)
            along = np.outer(np.linspace(-0.5, 0.5, 5) * length, [np.cos(yaw), np.sin(yaw)])
            ends = np.array([[x, y]]) + along
            height = rng.uniform(1.0, 2.5)
            if clear(ends, 0.85 * width):
                parts.append(_box((x, y, height / 2), (length, 0.3, height), yaw))
    mesh = parts[0]
    for p in parts[1:]:
        mesh += p
    return mesh
