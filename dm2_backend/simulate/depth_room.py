"""A simulated hand-held depth camera in a furnished room, written in the 7-Scenes layout.

The narrow sensor the 3D simulations lacked: a Kinect-like pinhole camera (640 x 480, fx = fy = 585, 0.4-4 m,
axial noise 1.2 mm + 1.9 mm x (z - 0.4 m)^2 (Nguyen et al. 2012), depth rounded to the millimetre) ray-cast with
open3d into a room with cabinets, shelves and picture frames along the walls, a table with things on it and
chairs. Four paths:

- ``walk``: laps around the table, the camera at head height looking ahead at the furniture along the walls
  (RedKitchen-like);
- ``rpy``: the camera held at one place and turned about all three axes, tens of degrees a second, a few
  centimetres of hand motion (TUM fr1_rpy-like): almost no translation, so little parallax to hold it;
- ``across``: round the room near the walls, looking across it at the table (median depth about 2.7 m, up to
  4 m: the noisiest depth);
- ``hall``: 2.5 m a lap walked slowly in a large hall with pillars (18 x 12 x 5 m), the camera panning across it:
  the range reaches 8 m, where a Kinect v1's depth is 4-11 cm noisy (the same noise model, extrapolated) and comes
  in steps of 5-18 cm (its disparity in steps of 1/8 pixel), and the near returns are mostly floor.

Written: ``frame-NNNNNN.depth.png`` (16-bit, millimetres), ``frame-NNNNNN.pose.txt`` (the true camera-to-world
pose), ``camera-intrinsics.txt``, ``truth.tum``, ``warm_start.tum`` (a drifting visual odometry), ``info.json``
and ``README.txt`` (the folder labelled SIMULATED).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from PIL import Image
from scipy.spatial.transform import Rotation

from dm2_backend import __version__
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.formats.tum import write_tum
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.simulate.path import drifting_odometry
from dm2_backend.simulate.scene import _box
from dm2_backend.simulate.sequence import _ate

PATHS = ("walk", "rpy", "across", "hall")
ROOM = (6.0, 5.0, 2.8)  # x, y, height (m); the floor at z = 0, the room centred on x = y = 0
HALL = (18.0, 12.0, 5.0)


@dataclass
class DepthCamera:
    """A pinhole depth camera (the 7-Scenes Kinect's intrinsics) and its noise."""

    width: int = 640
    height: int = 480
    fx: float = 585.0
    fy: float = 585.0
    cx: float = 320.0
    cy: float = 240.0
    min_depth: float = 0.4
    max_depth: float = 4.0
    dropout: float = 0.03
    #: depth from disparity in steps of this many pixels over a baseline (m) of ``baseline``: a depth step of
    #: z^2 * step / (fx * baseline) (a Kinect v1: 1/8 pixel over 7.5 cm, 4.6 cm at 4 m); 0: no steps (the depth is
    #: rounded to the millimetre either way)
    disparity_step: float = 0.0
    baseline: float = 0.075

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise (m) at depth ``z`` (Nguyen, Izadi, Lovell 2012, for a Kinect v1)."""
        return 0.0012 + 0.0019 * (z - 0.4) ** 2

    def quantise(self, z: np.ndarray) -> np.ndarray:
        """Depth ``z`` (m, 0 where invalid) as the camera reports it: through disparity steps, if any."""
        if not self.disparity_step:
            return z
        k = self.fx * self.baseline / self.disparity_step  # depth = k / disparity in steps
        steps = np.rint(k / np.where(z > 0, z, np.inf))
        return np.where((z > 0) & (steps > 0), k / np.maximum(steps, 1), 0.0)

    def rays(self) -> np.ndarray:
        """(H * W, 3) camera-frame directions with z = 1 (x right, y down, z forward), row-major."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, float)], -1).reshape(-1, 3)


def _along_walls(rng: np.random.Generator, room: tuple[float, float, float]) -> list[o3d.geometry.TriangleMesh]:
    """Cabinets, shelves and things on them along every wall, picture frames on the walls between them."""
    X, Y, _ = room
    parts = []
    for wall in range(4):
        length = X if wall % 2 == 0 else Y
        u = -length / 2 + rng.uniform(0.1, 0.5)
        while u < length / 2 - 0.5:
            width = rng.uniform(0.5, 1.2)
            if rng.uniform() < 0.7:  # a cabinet, with a few things on it
                depth, height = rng.uniform(0.35, 0.6), rng.uniform(0.5, 2.0)
                items = [((u + width / 2, depth / 2, height / 2), (width, depth, height))]
                for _ in range(rng.integers(0, 3)):
                    size = rng.uniform(0.08, 0.3, 3)
                    items.append(((u + rng.uniform(0.1, width - 0.1), depth / 2, height + size[2] / 2), size))
            else:  # a picture frame
                items = [((u + width / 2, 0.015, rng.uniform(1.2, 1.8)), (width, 0.03, rng.uniform(0.3, 0.7)))]
            for (a, b, z), size in items:  # wall coordinates (along, out of the wall) -> room coordinates
                if wall == 0:
                    centre, dims = (a, -Y / 2 + b, z), size
                elif wall == 1:
                    centre, dims = (X / 2 - b, a, z), (size[1], size[0], size[2])
                elif wall == 2:
                    centre, dims = (-a, Y / 2 - b, z), size
                else:
                    centre, dims = (-X / 2 + b, -a, z), (size[1], size[0], size[2])
                parts.append(_box(centre, dims))
            u += width + rng.uniform(0.1, 0.8)
    return parts


def room_mesh(seed: int, hall: bool = False) -> o3d.geometry.TriangleMesh:
    """Floor, ceiling, four walls, furniture along them and a table with chairs in the middle, placed from
    ``seed`` (the layout varies, the kind of room not); the ``hall`` (``HALL``, not ``ROOM``) also has pillars."""
    rng = np.random.default_rng([seed, 31])
    room = HALL if hall else ROOM
    X, Y, H = room
    parts = [_box((0, 0, -0.05), (X + 0.2, Y + 0.2, 0.1)), _box((0, 0, H + 0.05), (X + 0.2, Y + 0.2, 0.1)),
             _box((X / 2 + 0.05, 0, H / 2), (0.1, Y, H)), _box((-X / 2 - 0.05, 0, H / 2), (0.1, Y, H)),
             _box((0, Y / 2 + 0.05, H / 2), (X, 0.1, H)), _box((0, -Y / 2 - 0.05, H / 2), (X, 0.1, H))]
    parts += _along_walls(rng, room)
    if hall:  # two rows of pillars
        parts += [_box((x, y, H / 2), (0.4, 0.4, H)) for x in (-X / 4, X / 4) for y in (-Y / 4, Y / 4)]
    tx, ty, yaw = rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.3)
    c, s = np.cos(yaw), np.sin(yaw)
    parts.append(_box((tx, ty, 0.74), (1.2, 0.7, 0.04), yaw))                # table top
    for lx, ly in ((0.55, 0.3), (-0.55, 0.3), (0.55, -0.3), (-0.55, -0.3)):
        parts.append(_box((tx + c * lx - s * ly, ty + s * lx + c * ly, 0.36), (0.05, 0.05, 0.72), yaw))
    for _ in range(5):  # things on the table
        lx, ly, size = rng.uniform(-0.45, 0.45), rng.uniform(-0.22, 0.22), rng.uniform(0.08, 0.3, 3)
        parts.append(_box((tx + c * lx - s * ly, ty + s * lx + c * ly, 0.76 + size[2] / 2), size, rng.uniform(0, 3)))
    for side in (-1, 1):  # chairs: a seat and a back
        cx, cy = tx + side * 0.85 * c, ty + side * 0.85 * s
        parts += [_box((cx, cy, 0.45), (0.45, 0.45, 0.05), yaw),
                  _box((cx + side * 0.22 * c, cy + side * 0.22 * s, 0.7), (0.04, 0.45, 0.5), yaw)]
    mesh = o3d.geometry.TriangleMesh()
    for p in parts:
        mesh += p
    return mesh


def _look(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation of a camera at ``eye`` looking at ``target``, level (x right, y down, z forward)."""
    f = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.column_stack([right, np.cross(f, right), f])


def camera_path(kind: str, frames: int, laps: float, seed: int) -> np.ndarray:
    """True camera-to-world poses (frames, 4, 4) at 30 Hz."""
    if kind not in PATHS:
        raise ValueError(f"unknown path {kind!r} (choose from {', '.join(PATHS)})")
    rng = np.random.default_rng([seed, 32])
    phase = rng.uniform(0, 2 * np.pi, 6)
    t = np.arange(frames) / 30.0
    poses = np.tile(np.eye(4), (frames, 1, 1))
    if kind == "rpy":  # about 40 deg/s in each axis, the hand drifting a few centimetres
        eye = np.array([-1.6, -0.4, 1.4]) + 0.03 * np.sin(np.outer(t, [0.9, 1.3, 1.1]) + phase[:3])
        base = _look(eye[0], np.array([0.5, 0.3, 0.9]))
        angles = np.stack([0.35 * np.sin(2 * np.pi * t / 3.1 + phase[3]),    # roll about the optical axis
                           0.25 * np.sin(2 * np.pi * t / 2.3 + phase[4]),    # pitch
                           0.45 * np.sin(2 * np.pi * t / 4.2 + phase[5])], -1)  # yaw
        turn = Rotation.from_euler("zxy", angles).as_matrix()  # about the camera's z (roll), x (pitch), y (yaw)
        poses[:, :3, :3] = base @ turn
        poses[:, :3, 3] = eye
        return poses
    if kind == "hall":  # 2.5 m a lap walked towards the hall's middle, swaying, the camera panning across the hall
        u = laps * np.arange(frames) / max(frames, 1)
        eye = np.stack([-6.0 + 2.5 * u + 0.05 * np.sin(1.3 * t + phase[0]), -1.0 + 0.3 * np.sin(2 * np.pi * u),
                        1.45 + 0.05 * np.sin(0.9 * t + phase[1])], -1)
        look = 0.9 * np.sin(2 * np.pi * t / 12.0 + phase[2])
        target = eye + np.stack([6.0 * np.cos(look), 6.0 * np.sin(look), -0.6 + 0.3 * np.sin(0.4 * t + phase[3])], -1)
        for i in range(frames):
            poses[i, :3, :3] = _look(eye[i], target[i])
        poses[:, :3, 3] = eye
        return poses
    a = np.linspace(0, 2 * np.pi * laps, frames, endpoint=False)
    rx, ry = (1.1, 0.8) if kind == "walk" else (1.9, 1.5)
    eye = np.stack([rx * np.cos(a), ry * np.sin(a), 1.45 + 0.1 * np.sin(0.7 * t + phase[0])], -1)
    if kind == "walk":  # around the table, looking at the furniture along the walls ahead and outwards
        look = a + np.pi / 2 - 0.5 + 0.3 * np.sin(0.5 * t + phase[1])  # ahead, turned towards the walls
        target = eye + np.stack([2.5 * np.cos(look), 2.5 * np.sin(look), -0.9 + 0.3 * np.sin(0.4 * t + phase[2])], -1)
    else:  # across: round the room near the walls, looking across it at the table (far, noisy depth)
        target = np.stack([0.6 * np.cos(0.31 * t + phase[1]), 0.5 * np.sin(0.23 * t + phase[2]),
                           0.8 + 0.2 * np.sin(0.4 * t + phase[3])], -1)
    for i in range(frames):
        poses[i, :3, :3] = _look(eye[i], target[i])
    poses[:, :3, 3] = eye
    return poses


def depth_image(scene: o3d.t.geometry.RaycastingScene, camera: DepthCamera, rays: np.ndarray, pose: np.ndarray,
                rng: np.random.Generator) -> np.ndarray:
    """The uint16 depth image (millimetres, 0 where nothing valid) of the camera at ``pose``."""
    d = rays @ pose[:3, :3].T
    origin = np.broadcast_to(pose[:3, 3], d.shape)
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, d], 1).astype(np.float32)))
    z = hit["t_hit"].numpy().astype(np.float64)  # |d| has z = 1 in the camera frame: t is the depth
    valid = np.isfinite(z) & (z > camera.min_depth) & (z < camera.max_depth)
    valid &= rng.uniform(size=len(z)) >= camera.dropout
    z = np.where(valid, z + rng.normal(0, 1, len(z)) * camera.sigma(np.where(valid, z, 1.0)), 0.0)
    z = camera.quantise(z)
    return np.clip(np.rint(z * 1000), 0, 65534).astype(np.uint16).reshape(camera.height, camera.width)


def write_depth_room(out: Path, frames: int, path: str = "walk", laps: float = 1.0, seed: int = 0,
                     progress: bool = True) -> dict:
    """Simulate ``frames`` depth frames along ``path`` into ``out`` (the 7-Scenes layout); returns the info."""
    out = Path(out)
    t0 = time.perf_counter()
    hall = path == "hall"
    camera = DepthCamera(max_depth=8.0, disparity_step=0.125) if hall else DepthCamera()
    room = HALL if hall else ROOM
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(room_mesh(seed, hall)))
    gt = camera_path(path, frames, laps, seed)
    times = np.arange(frames) / 30.0
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    turn = se3.rotation_angle(se3.relative(gt[:-1], gt[1:])[:, :3, :3])
    # a visual odometry's drift (per frame, 30 a second): 5 % of the step, 2 mrad about the optical axis and 1 mrad
    # about the others, 0.5 mrad of bias
    warm = drifting_odometry(gt, seed + 1, yaw_sigma=0.002, trans_sigma=0.05, yaw_bias=0.0005, z_sigma=0.05,
                             tilt_sigma=0.001)
    out.mkdir(parents=True, exist_ok=True)
    rays = camera.rays()
    valid = np.zeros(frames)
    for i in progress_of(range(frames), "simulate", unit="frame", enabled=progress):
        img = depth_image(scene, camera, rays, gt[i], np.random.default_rng([seed, 33, i]))
        valid[i] = (img > 0).mean()
        with atomic_write(out / f"frame-{i:06d}.depth.png", "wb") as fh:
            Image.fromarray(img).save(fh, format="PNG")
        with atomic_write(out / f"frame-{i:06d}.pose.txt") as fh:
            np.savetxt(fh, gt[i], fmt="%.9f")
    with atomic_write(out / "camera-intrinsics.txt") as fh:
        np.savetxt(fh, [[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], fmt="%.6f")
    write_tum(Trajectory(gt, times), out / "truth.tum", ReadOptions())
    write_tum(Trajectory(warm, times), out / "warm_start.tum", ReadOptions())
    info = {"simulated": True, "generator": f"dm2 simulate --scene room (dm2 {__version__})",
            "frames": frames, "path": path, "laps": laps, "seed": seed, "camera": asdict(camera),
            "room_m": list(room), "valid_pixels": float(valid.mean()),
            "path_length_m": float(steps.sum()), "median_step_m": float(np.median(steps)) if frames > 1 else 0.0,
            "median_turn_deg": float(np.degrees(np.median(turn))) if frames > 1 else 0.0,
            "warm_start": {"ate_rmse_m": _ate(gt, warm)}, "seconds": round(time.perf_counter() - t0, 3)}
    with atomic_write(out / "info.json") as fh:
        json.dump(info, fh, indent=2)
    with atomic_write(out / "README.txt") as fh:
        fh.write(_readme(info))
    return info


def _readme(info: dict) -> str:
    """``README.txt`` of a room folder: labelled SIMULATED, what made it, what each file holds."""
    cam = info["camera"]
    quantised = (f", depth in disparity steps of 1/{1 / cam['disparity_step']:g} pixel over {cam['baseline']:g} m"
                 if cam["disparity_step"] else "")
    room = " x ".join(f"{v:g}" for v in info["room_m"])
    return f"""SIMULATED DATA - not recorded by a real sensor.

Generated by {info['generator']}: a hand-held depth camera ({cam['width']} x {cam['height']}, fx {cam['fx']:g},
{cam['min_depth']:g}-{cam['max_depth']:g} m, axial noise 1.2 mm + 1.9 mm x (z - 0.4 m)^2, {100 * cam['dropout']:g} % of
the pixels dropped{quantised}) in a furnished {room} m room, path '{info['path']}',
{info['frames']} frames at 30 Hz, seed {info['seed']}, {info['path_length_m']:.1f} m.

frame-NNNNNN.depth.png  depth, 16-bit millimetres, 0 where nothing valid (the 7-Scenes layout)
frame-NNNNNN.pose.txt   the true camera-to-world pose (4 x 4)
camera-intrinsics.txt   the pinhole matrix
truth.tum               ground truth, TUM format
warm_start.tum          a drifting visual odometry, TUM format (ATE {info['warm_start']['ate_rmse_m']:.3f} m)
info.json               every setting

Refine it: dm2 refine --scans FOLDER --poses FOLDER/warm_start.tum --gt FOLDER/truth.tum --out RUN
"""
