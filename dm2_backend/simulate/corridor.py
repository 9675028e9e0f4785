"""A building where 2D laser scan matching degenerates: a ring of long featureless corridors (a hospital or
office floor), driven in laps with drifting wheel odometry, scanned by a planar laser whose range is shorter
than the corridors (so the far end walls are out of sight and sliding along a corridor costs nothing).

The ring is ``length`` x ``width`` metres (centre line), corridors ``corridor`` metres wide; the only
features are a few door niches on the outer wall of the long sides, far apart. ``corridor_sequence`` returns
the scans (sensor frame, z = 0), the true poses and the odometry poses; ``write_corridors`` writes them as
``dm2 simulate --scene corridors`` does.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from dm2_backend import __version__
from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.simulate.lidar import LidarModel, Raycaster
from dm2_backend.simulate.path import drifting_odometry
from dm2_backend.simulate.sequence import write_sequence


def _boxes(rects, z0: float = -1.0, z1: float = 3.0) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh()
    for x0, y0, x1, y1 in rects:
        mesh += o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0).translate((x0, y0, z0))
    return mesh


def corridor_walls(length: float = 40.0, width: float = 14.0, corridor: float = 2.0, doors: int = 3,
                   thick: float = 0.2) -> list[tuple[float, float, float, float]]:
    """Wall rectangles (x0, y0, x1, y1) of the ring around the centre line [0, length] x [0, width], with
    ``doors`` niches (1 m wide, 0.5 m deep) in the outer wall of each long side."""
    h = corridor / 2.0
    ox0, oy0, ox1, oy1 = -h, -h, length + h, width + h  # outer wall's inner face
    ix0, iy0, ix1, iy1 = h, h, length - h, width - h  # inner block
    rects = [(ix0, iy0, ix1, iy1),  # the inner block, solid
             (ox0 - thick, oy0, ox0, oy1), (ox1, oy0, ox1 + thick, oy1)]  # the short outer walls
    xs = np.linspace(0.0, length, doors + 2)[1:-1]
    for y_face, outward in ((oy0, -1.0), (oy1, 1.0)):
        edges = [ox0 - thick] + [v for x in xs for v in (x - 0.5, x + 0.5)] + [ox1 + thick]
        for a, b in zip(edges[::2], edges[1::2]):  # wall segments between the niches
            y0, y1 = sorted((y_face, y_face + outward * thick))
            rects.append((a, y0, b, y1))
        for x in xs:  # each niche: a back wall 0.5 m out, and its sides
            back = y_face + outward * 0.5
            y0, y1 = sorted((back, back + outward * thick))
            rects.append((x - 0.5 - thick, y0, x + 0.5 + thick, y1))
            for sx in (x - 0.5 - thick, x + 0.5):
                y0, y1 = sorted((y_face, back))
                rects.append((sx, y0, sx + thick, y1))
    return rects


def ring_path(length: float, width: float, step: float, laps: float, radius: float = 0.8) -> np.ndarray:
    """Planar poses every ``step`` m along the ring's centre line (counter-clockwise, corners rounded with
    ``radius``), heading along the path."""
    r = radius
    pts = []
    corners = [((length - r, r), -np.pi / 2), ((length - r, width - r), 0.0), ((r, width - r), np.pi / 2),
               ((r, r), np.pi)]
    for (cx, cy), a0 in corners:
        for a in np.linspace(a0, a0 + np.pi / 2, 12):
            pts.append((cx + r * np.cos(a), cy + r * np.sin(a)))
    pts = np.array(pts + [pts[0]])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1] * laps, step) % s[-1]
    xy = np.column_stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])])
    ahead = np.column_stack([np.interp((t + step) % s[-1], s, pts[:, 0]), np.interp((t + step) % s[-1], s, pts[:, 1])])
    yaw = np.arctan2(ahead[:, 1] - xy[:, 1], ahead[:, 0] - xy[:, 0])
    return se3.from_xy_yaw(np.column_stack([xy, yaw]))


def corridor_sequence(length: float = 40.0, width: float = 14.0, step: float = 0.25, laps: float = 1.3,
                      max_range: float = 8.0, seed: int = 0, yaw_sigma: float = 0.002, trans_sigma: float = 0.03,
                      yaw_bias: float = 0.001, range_noise: float = 0.02, front_only: bool = True,
                      ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Scans (sensor frame, z = 0; 1-degree beams, the front half only by default, as a SICK LMS of the
    CARMEN logs), true poses and drifting odometry (per step: yaw noise and bias in rad, translation noise as
    a fraction of the step) along ``laps`` laps of the corridor ring."""
    truth = ring_path(length, width, step, laps)
    model = LidarModel(planar=True, columns=360, max_range=max_range, range_noise=range_noise, dropout=0.02,
                       height=1.0)
    caster = Raycaster(_boxes(corridor_walls(length, width)), model)
    rng = np.random.default_rng(seed)
    scans = []
    for T in truth:
        p = caster.scan(T, rng) * np.array([1, 1, 0], np.float32)
        scans.append(p[p[:, 0] >= 0] if front_only else p)
    odometry = drifting_odometry(truth, seed + 1, yaw_sigma, trans_sigma, yaw_bias)
    return scans, truth, odometry


#: spacing of the corridor ring's frames (m) and the ring's default size: ``length`` + ``width`` make the lap
STEP, LENGTH, WIDTH = 0.25, 40.0, 14.0


def write_corridors(out: Path, frames: int, seed: int = 0, rate_hz: float = 10.0, max_range: float = 8.0,
                    yaw_bias: float = 0.004, yaw_noise: float = 0.004, trans_noise: float = 0.03) -> dict:
    """``dm2 simulate --scene corridors``: ``frames`` scans of the corridor ring (one every 0.25 m) in the
    layout of :func:`~dm2_backend.simulate.sequence.write_sequence`, the drifting odometry as
    ``warm_start.txt``; drift per metre (yaw bias, rad), per square-root metre (yaw noise, rad) and as a
    fraction of each step (translation). Returns the ``info.json`` it writes."""
    t0 = time.perf_counter()
    lap = 2.0 * (LENGTH + WIDTH)
    scans, truth, odometry = corridor_sequence(
        LENGTH, WIDTH, STEP, laps=1.05 * frames * STEP / lap, max_range=max_range, seed=seed,
        yaw_sigma=yaw_noise * np.sqrt(STEP), trans_sigma=trans_noise, yaw_bias=yaw_bias * STEP)
    scans, truth, odometry = scans[:frames], truth[:frames], odometry[:frames]
    write_sequence(out, scans, truth, odometry, rate_hz)
    err = np.linalg.norm(odometry[:, :2, 3] - truth[:, :2, 3], axis=1)
    info = {
        "simulated": True, "generator": f"dm2 simulate --scene corridors (dm2 {__version__})",
        "settings": {"scene": "corridors", "frames": frames, "seed": seed, "rate_hz": rate_hz, "step_m": STEP,
                     "ring_m": [LENGTH, WIDTH], "corridor_m": 2.0, "max_range_m": max_range, "front_only": True,
                     "yaw_bias": yaw_bias, "yaw_noise": yaw_noise, "trans_noise": trans_noise},
        "frames": frames, "path_length_m": float(STEP * (frames - 1)),
        "points_per_frame": {"mean": float(np.mean([len(s) for s in scans]))},
        "warm_start": {"max_position_error_m": float(err.max()), "final_position_error_m": float(err[-1])},
        "seconds": round(time.perf_counter() - t0, 3),
    }
    with atomic_write(Path(out) / "info.json") as fh:
        json.dump(info, fh, indent=2)
    with atomic_write(Path(out) / "README.txt") as fh:
        fh.write(f"""SIMULATED DATA - not recorded by a real sensor.

Generated by {info['generator']}: a ring of featureless 2 m corridors ({LENGTH:g} x {WIDTH:g} m, a few door
niches) scanned by a planar laser that sees the front half only, {max_range:g} m range, shorter than the
corridors: scan matching cannot tell where it is along a corridor. {frames} frames, one every {STEP} m.

velodyne/NNNNNN.bin  scans, float32 x y z intensity (sensor frame; z = 0)
times.txt            one timestamp (s) per scan
poses.txt            ground truth, KITTI format
warm_start.txt       drifting wheel odometry, KITTI format (largest error {err.max():.2f} m)
info.json            every setting used

Refine it:  dm2 refine --scans velodyne --poses warm_start.txt --warm-start icp --gt poses.txt --out run
""")
    return info
