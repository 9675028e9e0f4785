"""The simulator through a real map: the mesh of real LiDAR keyframes reproduces the scans it was made from,
and the path between keyframes is interpolated on SE(3)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from shared_helpers import DATA, need

from dm2_backend.formats.registry import ReadOptions
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.simulate.lidar import LidarModel, Raycaster
from dm2_backend.simulate.real_map import denser, map_mesh


def test_denser_poses_interpolate_on_se3():
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    b[:3, 3] = [2.0, 0.0, 1.0]
    out = denser(np.stack([a, b, a]), 4)
    assert len(out) == 9
    np.testing.assert_allclose(out[[0, 4, 8]], np.stack([a, b, a]), atol=1e-12)
    np.testing.assert_allclose(out[2, :3, 3], [1.0, 0.0, 0.5])
    assert abs(Rotation.from_matrix(out[2, :3, :3]).as_euler("zyx", degrees=True)[0] - 20.0) < 1e-6


def test_the_mesh_of_real_keyframes_reproduces_their_scans():
    folder = need(DATA / "lidar3d" / "balm_realworld_000-079")
    real = load_inputs(folder / "velodyne", None, folder / "poses.txt", None, ReadOptions(times=folder / "times.txt"))
    keep = list(range(0, 20, 2))
    poses = real.given.poses[keep]
    scans = [real.scans[i] for i in keep]
    mesh = map_mesh(scans, poses, voxel=0.1, reach=20.0, depth=9)
    assert len(mesh.triangles) > 10_000
    caster = Raycaster(mesh, LidarModel(beams=32, fov_up_deg=45, fov_down_deg=-45, columns=720, max_range=20.0,
                                        range_noise=0.0, dropout=0.0))
    simulated = caster.scan(poses[4], np.random.default_rng(0))
    original = np.asarray(scans[4].points)[:, :3]
    original = original[np.linalg.norm(original, axis=1) < 15.0]
    gap, _ = cKDTree(original).query(simulated[np.linalg.norm(simulated, axis=1) < 15.0])
    assert len(simulated) > 5_000 and np.median(gap) < 0.15  # the real scan is voxelised to 0.1 m
