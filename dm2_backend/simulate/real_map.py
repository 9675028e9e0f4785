"""A simulated LiDAR sequence through a real map: the truth known, the geometry not procedural.

The map is a mesh reconstructed from real scans at their poses (open3d's screened Poisson reconstruction of
their merged points, normals oriented towards the sensor that saw them); the sensor then drives a path through
it (the scans' own poses, made denser by interpolation) and each frame is ray-cast into the mesh with range
noise, as :mod:`dm2_backend.simulate.sequence` does for its procedural street. The blur of the real poses does
not matter: the mesh *is* the world of the simulation, so its own poses are the ground truth.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from dm2_backend.formats.scan_folder import write_bin
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.simulate.lidar import LidarModel, Raycaster
from dm2_backend.simulate.path import drifting_odometry
from dm2_backend.simulate.sequence import _ate, _write_trajectories


def map_mesh(scans: ScanSequence, poses: np.ndarray, voxel: float, reach: float,
             depth: int = 10) -> o3d.geometry.TriangleMesh:
    """The surface of the scans placed by ``poses``: their points within ``reach`` of the sensor merged on a
    ``voxel`` grid, isolated points dropped, each scan's normals turned towards its sensor, the Poisson surface
    of ``depth`` cut to the points' box, its least supported fifth (skin extrapolated over holes) removed."""
    merged = o3d.geometry.PointCloud()
    for scan, T in zip(scans, poses, strict=True):
        pts = np.asarray(scan.points, np.float64)[:, :3]
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[np.linalg.norm(pts, axis=1) < reach]))
        pcd = pcd.voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        merged += pcd.transform(T)
    merged = merged.voxel_down_sample(voxel)
    merged, _ = merged.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(merged, depth=depth)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.2))
    return mesh.crop(merged.get_axis_aligned_bounding_box())


def denser(poses: np.ndarray, factor: int) -> np.ndarray:
    """``factor`` poses per interval of ``poses`` (rotation by slerp, translation linearly), the last kept."""
    t = np.arange(len(poses), dtype=float)
    return se3.interpolate(t, poses, np.linspace(0, len(poses) - 1, (len(poses) - 1) * factor + 1))


def write_real_map_sequence(out: Path, scans: ScanSequence, poses: np.ndarray, model: LidarModel,
                            factor: int = 2, seed: int = 0, rate_hz: float = 10.0) -> dict:
    """Ray-cast a sequence through the mesh of ``scans`` at ``poses`` into a KITTI-odometry folder (as ``dm2
    simulate`` writes: ``velodyne/``, ``poses.txt`` the truth, ``warm_start.txt`` a drifting odometry,
    ``times.txt``, ``info.json``, and the mesh as ``map.ply``). Returns the info."""
    out = Path(out)
    t0 = time.perf_counter()
    spacing = float(np.median(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)))
    voxel = max(model.range_noise, 0.05)
    mesh = map_mesh(scans, poses, voxel, model.max_range)
    caster = Raycaster(mesh, model)
    gt = denser(poses, factor)
    step = spacing / factor
    warm = drifting_odometry(gt, seed + 1, yaw_sigma=0.001 * np.sqrt(step), trans_sigma=0.02, yaw_bias=0.00035 * step,
                             z_sigma=0.01, tilt_sigma=0.0003 * np.sqrt(step))
    counts = []
    for i, T in enumerate(gt):
        points, intensity = caster.scan_with_intensity(T, np.random.default_rng([seed, 1, i]))
        write_bin(out / "velodyne" / f"{i:06d}.bin", points, intensity)
        counts.append(len(points))
    _write_trajectories(out, gt, warm, np.arange(len(gt)) / rate_hz)
    o3d.io.write_triangle_mesh(str(out / "map.ply"), mesh)
    info = {"simulated": True, "map": f"Poisson mesh of {len(scans)} real scans at their poses (voxel {voxel} m)",
            "frames": len(gt), "triangles": len(mesh.triangles), "points_per_frame": float(np.mean(counts)),
            "path_length_m": float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()),
            "lidar": {k: getattr(model, k) for k in ("beams", "columns", "fov_up_deg", "fov_down_deg", "max_range",
                                                      "range_noise", "dropout")},
            "warm_start": {"ate_rmse_m": _ate(gt, warm)}, "seconds": time.perf_counter() - t0}
    with atomic_write(out / "info.json") as fh:
        json.dump(info, fh, indent=2)
    return info
