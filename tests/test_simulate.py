"""The LiDAR simulator: determinism, planar scans, paths that revisit places, drift, the written folder
and ``dm2 simulate``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.simulate.lidar import LidarModel
from dm2_backend.simulate.path import street_path
from dm2_backend.simulate.sequence import SimSettings, Simulation, generate


def small(**kw) -> SimSettings:
    """A coarse 8-beam LiDAR so that the tests stay fast."""
    planar = kw.get("planar", False)
    lidar = LidarModel(beams=8, columns=120, planar=planar, height=0.5 if planar else 1.8)
    return SimSettings(**{"frames": 40, "seed": 3, "lidar": lidar, **kw})


def test_same_seed_same_sequence_other_seed_differs():
    a, b, c = Simulation(small()), Simulation(small()), Simulation(small(seed=4))
    for i in (0, 17, 39):
        pa, ia = a.scan(i)
        pb, ib = b.scan(i)
        assert np.array_equal(pa, pb) and np.array_equal(ia, ib)
        assert len(pa) > 200
    assert np.array_equal(a.gt, b.gt) and np.array_equal(a.warm, b.warm)
    assert not np.allclose(a.gt, c.gt)
    assert not np.array_equal(a.scan(5)[0][:100], c.scan(5)[0][:100])
    # a frame does not depend on which frames were simulated before it
    assert np.array_equal(Simulation(small()).scan(17)[0], a.scan(17)[0])


def test_3d_scans_see_ground_and_structure_and_the_street_is_free():
    sim = Simulation(small(frames=12))
    assert np.allclose(sim.gt[:, 2, 3], 1.8)
    for i in range(0, 12, 4):
        p, intensity = sim.scan(i)
        assert np.abs(np.median(p[p[:, 2] < -1.0, 2]) + 1.8) < 0.05  # the ground, 1.8 m below the sensor
        above = p[p[:, 2] > -1.0]
        assert (above[:, 2] > 2.0).any()  # buildings / poles higher than the sensor
        assert np.hypot(above[:, 0], above[:, 1]).min() > 2.0  # nothing stands on the street
        assert intensity.min() >= 0 and intensity.max() <= 1


def test_planar_scans_are_flat_and_poses_planar():
    sim = Simulation(small(planar=True, path="eight"))
    for i in (0, 20):
        p, _ = sim.scan(i)
        assert len(p) > 30 and np.all(p[:, 2] == 0)
    assert se3.is_planar(sim.gt) and se3.is_planar(sim.warm)


@pytest.mark.parametrize("kind", ["loop", "eight"])
def test_paths_revisit_places(kind):
    poses = street_path(kind, 300, 28.0, 3, seed=1)
    xy = poses[:, :2, 3]
    assert np.allclose(xy[:100], xy[100:200], atol=1e-6) and np.allclose(xy[:100], xy[200:], atol=1e-6)
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert step.std() < 0.05 * step.mean()  # constant speed
    chord = np.arctan2(np.diff(xy[:, 1]), np.diff(xy[:, 0]))
    yaw = se3.to_xy_yaw(poses)[:, 2]
    mid = yaw[:-1] + se3.wrap_angle(yaw[1:] - yaw[:-1]) / 2  # heading along the path: the chord's direction
    assert np.abs(se3.wrap_angle(chord - mid)).max() < 0.02
    if kind == "eight":  # passes the crossing at the origin twice per lap, in two directions
        near = np.flatnonzero(np.linalg.norm(xy[:100], axis=1) < 1.0)
        assert len(near) >= 2 and np.ptp(se3.to_xy_yaw(poses[near])[:, 2]) > 1.0


def test_warm_start_drifts_more_along_the_path():
    sim = Simulation(small(frames=400, lidar=LidarModel(beams=1, columns=4)))
    err = np.linalg.norm(sim.warm[:, :3, 3] - sim.gt[:, :3, 3], axis=1)
    assert err[0] == 0 and err[-100:].mean() > 3 * err[:100].mean() > 0
    yaw_err = se3.wrap_angle(se3.to_xy_yaw(sim.warm)[:, 2] - se3.to_xy_yaw(sim.gt)[:, 2])
    assert abs(yaw_err[-1]) > abs(yaw_err[50])
    assert np.abs(sim.warm[:, 2, 3] - 1.8).max() > 0  # 3D drift includes z


def test_written_folder_reads_back(tmp_path):
    s = small(frames=10)
    info = generate(s, tmp_path, progress=False)
    assert info["simulated"] and info["frames"] == 10 and info["settings"]["lidar"]["beams"] == 8
    assert "SIMULATED" in (tmp_path / "README.txt").read_text()
    seq = open_scans(tmp_path / "velodyne", None, ReadOptions())
    sim = Simulation(s)
    assert len(seq) == 10 and np.allclose(seq.timestamps, np.arange(10) / 10.0)
    for i in (0, 9):
        points, intensity = sim.scan(i)
        assert np.array_equal(seq[i].points, points.astype(np.float64))
        assert np.array_equal(seq[i].intensity, intensity)
    gt = read_trajectory(tmp_path / "poses.txt")
    warm = read_trajectory(tmp_path / "warm_start.txt", "kitti")
    assert np.array_equal(gt.poses, sim.gt) and np.allclose(warm.poses, sim.warm, atol=1e-12)
    assert np.allclose(gt.timestamps, seq.timestamps)
    assert info["warm_start"]["ate_rmse_m"] > 0


def test_cli_writes_a_labelled_folder_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "sim"
    args = ["simulate", "-n", "6", "--beams", "4", "--columns", "60", "--seed", "2", "-o", str(out), "-q"]
    result = CliRunner().invoke(cli, args, obj={})
    assert result.exit_code == 0, result.output
    assert len(list((out / "velodyne").glob("*.bin"))) == 6
    info = json.loads((out / "info.json").read_text())
    assert info["simulated"] is True
    assert info["settings"]["lidar"]["beams"] == 4 and info["settings"]["seed"] == 2
    result = CliRunner().invoke(cli, args, obj={})
    assert result.exit_code == 2 and "not empty" in result.output and str(out) in result.output
    assert len(result.output.strip().splitlines()) == 1
    args_planar = ["simulate", "-n", "4", "--planar", "-o", str(out), "-q", "--force"]
    result = CliRunner().invoke(cli, args_planar, obj={})
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == [f"{i:06d}.bin" for i in range(4)]
    seq = open_scans(out / "velodyne", None, ReadOptions())
    assert seq.planar or np.all(seq[0].points[:, 2] == 0)
    result = CliRunner().invoke(cli, ["simulate", "-n", "4", "-o", str(out / "README.txt")], obj={})
    assert result.exit_code == 2 and "not a folder" in result.output


def test_cli_simulates_the_corridor_ring(tmp_path):
    out = tmp_path / "corridors"
    args = ["simulate", "--scene", "corridors", "-n", "40", "--seed", "3", "-o", str(out), "-q"]
    result = CliRunner().invoke(cli, args, obj={})
    assert result.exit_code == 0, result.output
    info = json.loads((out / "info.json").read_text())
    assert info["simulated"] and info["settings"]["scene"] == "corridors" and info["frames"] == 40
    seq = open_scans(out / "velodyne", None, ReadOptions())
    assert len(seq) == 40
    pts = seq[5].points
    assert np.all(pts[:, 2] == 0) and pts[:, 0].min() >= 0  # planar, the front half only
    assert np.abs(pts[:, 1]).max() < 8.0 + 1e-3  # within range; the corridor walls 1 m either side dominate
    assert np.median(np.abs(pts[:, 1])) == pytest.approx(1.0, abs=0.3)
    gt = read_trajectory(out / "poses.txt")
    warm = read_trajectory(out / "warm_start.txt")
    steps = np.linalg.norm(np.diff(gt.poses[:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, 0.25, atol=0.02)  # on the straight; one every 0.25 m
    assert 0 < np.abs(warm.poses[:, :2, 3] - gt.poses[:, :2, 3]).max() < 2.0  # drifting odometry
