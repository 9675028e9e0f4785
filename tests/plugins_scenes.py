"""Small synthetic scenes for the preparation-plugin tests: a 2D floor (room A, a long featureless
corridor, room C) scanned by a planar laser, and a 3D box room scanned by a 16-beam LiDAR."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.prepare.frames import load_frames
from dm2_backend.simulate.lidar import LidarModel, Raycaster

#: rectangles (x0, y0, x1, y1) of solid walls and obstacles of the 2D floor
FLOOR = [
    # room A [0, 10] x [0, 8], door to the corridor at y in [3, 5]
    (-0.2, -0.2, 10.2, 0.0),
    (-0.2, 8.0, 10.2, 8.2),
    (-0.2, 0.0, 0.0, 8.0),
    (10.0, 0.0, 10.2, 3.0),
    (10.0, 5.0, 10.2, 8.0),
    (3.0, 5.0, 3.6, 5.4),
    (6.0, 6.6, 7.5, 7.2),
    (8.8, 0.0, 10.0, 0.9),
    (0.0, 2.8, 0.5, 3.4),
    # corridor x in [10, 40], y in [3, 5]
    (10.0, 2.8, 40.0, 3.0),
    (10.0, 5.0, 40.0, 5.2),
    # room C [40, 48] x [-2, 10]
    (40.0, -2.2, 48.2, -2.0),
    (40.0, 10.0, 48.2, 10.2),
    (48.0, -2.0, 48.2, 10.0),
    (40.0, -2.0, 40.2, 3.0),
    (40.0, 5.0, 40.2, 10.0),
    (44.0, 6.0, 44.6, 6.6),
    (45.0, -2.0, 46.5, -1.0),
    (42.0, 9.0, 43.5, 10.0),
]
#: waypoints: a lap of room A, out along the corridor, a lap of room C, back to room A's start
WAYPOINTS_2D = [
    (2, 1.5),
    (7.5, 1.5),
    (8.3, 4),
    (8, 6),
    (2, 6.2),
    (1.5, 4),
    (9, 4),
    (38, 4),
    (43, 4),
    (46, 2),
    (46.5, 7),
    (42, 7.5),
    (41.5, 4),
    (12, 4),
    (5, 4),
    (4.5, 2),
    (2.5, 1.6),
]


def box_mesh(rects, z0: float = -1.0, z1: float = 3.0) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh()
    for x0, y0, x1, y1 in rects:
        b = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
        mesh += b.translate((x0, y0, z0))
    return mesh


def polyline_path(waypoints, step: float, smooth: int = 5) -> np.ndarray:
    """Planar poses every ``step`` metres along the waypoints, heading along the (smoothed) path."""
    w = np.asarray(waypoints, dtype=float)
    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1], step)
    xy = np.column_stack([np.interp(t, s, w[:, 0]), np.interp(t, s, w[:, 1])])
    kernel = np.ones(smooth) / smooth
    pad = np.pad(xy, ((smooth // 2, smooth // 2), (0, 0)), mode="edge")
    xy = np.column_stack([np.convolve(pad[:, c], kernel, mode="valid") for c in range(2)])
    d = np.gradient(xy, axis=0)
    return se3.from_xy_yaw(np.column_stack([xy, np.arctan2(d[:, 1], d[:, 0])]))


def frames_from(scans: list[np.ndarray], planar: bool, max_points: int = 1024) -> Frames:
    """Frames through the real loader (down-sampling and derived length scales)."""
    seq = ScanSequence(
        loader=lambda i: Scan(scans[i]),
        count=len(scans),
        timestamps=np.arange(len(scans)) * 0.1,
        planar=planar,
        source="synthetic",
    )
    return load_frames(seq, max_points, progress=False)


def floor_2d(step: float = 0.5, seed: int = 0) -> tuple[Frames, np.ndarray]:
    """Planar laser frames (360 beams, 8 m) along the 2D floor path, and the true poses."""
    truth = polyline_path(WAYPOINTS_2D, step)
    model = LidarModel(planar=True, columns=360, max_range=8.0, range_noise=0.01, dropout=0.02, height=1.0)
    caster = Raycaster(box_mesh(FLOOR), model)
    rng = np.random.default_rng(seed)
    scans = [caster.scan(T, rng) * np.array([1, 1, 0], np.float32) for T in truth]
    return frames_from(scans, planar=True), truth


#: 3D box room 16 x 10 x 3 m with boxes and pillars
ROOM_3D = [
    (-0.2, -0.2, 16.2, 0.0),
    (-0.2, 10.0, 16.2, 10.2),
    (-0.2, 0.0, 0.0, 10.0),
    (16.0, 0.0, 16.2, 10.0),
    (1.5, 6.0, 2.5, 7.0),
    (9.0, 0.8, 11.0, 1.6),
    (12.5, 7.0, 13.0, 7.5),
    (6.0, 8.5, 8.0, 10.0),
]


def room_3d(count: int = 30, seed: int = 0, laps: int = 1) -> tuple[Frames, np.ndarray]:
    """16-beam LiDAR frames along ``laps`` loops (``count`` frames each, later laps 0.3 m further out) in
    the 3D box room (floor and ceiling included)."""
    mesh = box_mesh(ROOM_3D, 0.0, 3.0)
    mesh += box_mesh([(-0.2, -0.2, 16.2, 10.2)], -0.1, 0.0)  # floor
    mesh += box_mesh([(-0.2, -0.2, 16.2, 10.2)], 3.0, 3.1)  # ceiling
    a = np.linspace(0, 2 * np.pi * laps, count * laps, endpoint=False)
    grow = 0.3 * (a // (2 * np.pi))
    xy = np.column_stack([8 + (4.5 + grow) * np.cos(a), 5 + (2.5 + grow) * np.sin(a)])
    truth = se3.from_xy_yaw(np.column_stack([xy, a + np.pi / 2]))
    truth[:, 2, 3] = 1.2
    model = LidarModel(beams=16, fov_up_deg=15, fov_down_deg=-15, columns=360, max_range=20, range_noise=0.01)
    caster = Raycaster(mesh, model)
    rng = np.random.default_rng(seed)
    return frames_from([caster.scan(T, rng) for T in truth], planar=False), truth
