"""The hand-held depth camera simulation (``dm2 simulate --scene room``): a 7-Scenes folder whose depth agrees with
its true poses, the paths, and refine from the truth staying at the truth on a narrow, noisy sensor."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.formats import open_scans, read_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.simulate.depth_room import HALL, DepthCamera, camera_path, room_mesh, write_depth_room


def invoke(args: list[str]):
    return CliRunner().invoke(cli, args, obj={})


def test_the_depth_images_agree_with_the_true_poses(tmp_path):
    out = tmp_path / "walk"
    write_depth_room(out, 12, "walk", 0.05, seed=1, progress=False)
    scans = open_scans(out)
    truth = read_trajectory(out / "truth.tum").poses
    np.testing.assert_allclose(scans.trajectories["reference"].poses, truth, atol=1e-6)
    info = json.loads((out / "info.json").read_text())
    assert info["simulated"] and info["frames"] == 12 == len(scans)
    readme = (out / "README.txt").read_text()
    assert readme.startswith("SIMULATED DATA") and "path 'walk'" in readme and "12 frames" in readme
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(room_mesh(1)))
    camera = DepthCamera()
    for i in (0, 11):
        points = scans[i].points.astype(np.float64)  # every second pixel (the reader's default stride)
        world = se3.transform_points(truth[i], points)
        gap = scene.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        depth = points[:, 2]
        assert len(points) > 0.8 * 320 * 240 * (1 - camera.dropout)  # a closed room: almost every pixel returns
        assert np.median(gap) < 0.01 and np.mean(gap < 4 * camera.sigma(depth) + 0.001) > 0.99
        # at a wrong pose the same points are off the surfaces
        moved = se3.transform_points(truth[i] @ se3.from_xyz_euler(np.array([[0.05, 0, 0, 0, 0, 0.02]]))[0], points)
        assert np.median(scene.compute_distance(o3d.core.Tensor(moved.astype(np.float32))).numpy()) > 0.01


def test_rpy_turns_in_place_and_walk_goes_round():
    rpy, around = camera_path("rpy", 300, 1.0, 0), camera_path("walk", 600, 1.0, 0)
    assert np.ptp(rpy[:, :3, 3], axis=0).max() < 0.1  # the hand drifts a few centimetres ...
    turns = se3.rotation_angle(se3.relative(rpy[:1], rpy)[:, :3, :3])
    assert np.degrees(turns.max()) > 25  # ... while the camera turns by tens of degrees
    steps = np.linalg.norm(np.diff(around[:, :3, 3], axis=0), axis=1)
    assert 4 < steps.sum() < 8 and np.linalg.norm(around[-1, :3, 3] - around[0, :3, 3]) < 0.05  # one lap
    for poses in (rpy, around):
        np.testing.assert_allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.eye(3)[None].repeat(
            len(poses), 0), atol=1e-9)


def test_a_kinect_v1_reports_depth_in_disparity_steps():
    camera = DepthCamera(disparity_step=0.125)
    z = np.array([0.0, 1.0, 4.0, 4.01, 7.0])
    q = camera.quantise(z)
    k = camera.fx * camera.baseline / camera.disparity_step
    assert q[0] == 0.0 and np.allclose(k / q[1:], np.rint(k / q[1:]))  # every depth on a disparity step ...
    assert np.all(np.abs(q - z)[1:] <= 0.5 * z[1:] ** 2 / (k - 0.5 * z[1:]))  # ... the nearest: about half a step
    assert 0.04 < 16.0 / k < 0.05 and q[2] == q[3]  # 4.6 cm steps at 4 m: 1 cm apart reads the same
    assert np.array_equal(DepthCamera().quantise(z), z)  # the other paths' camera: only the millimetre rounding


def test_the_hall_is_far_noisy_and_quantised_and_its_depth_agrees_with_the_true_poses(tmp_path):
    for seed in range(10):
        path = camera_path("hall", 600, 1.0, seed)
        steps = np.linalg.norm(np.diff(path[:, :3, 3], axis=0), axis=1)
        assert 2.5 < steps.sum() < 3.5  # a lap: 2.5 m walked, swaying
        assert np.all(np.abs(path[:, :2, 3]) < np.array(HALL[:2]) / 2 - 2.0)  # inside, 2 m from the walls at least
        pan = np.degrees(se3.rotation_angle(se3.relative(path[:1], path)[:, :3, :3]))
        assert pan.max() > 45  # panning across the hall
    out = tmp_path / "hall"
    info = write_depth_room(out, 4, "hall", 0.01, seed=1, progress=False)
    assert info["room_m"] == list(HALL) and info["camera"]["disparity_step"] == 0.125
    scans, truth = open_scans(out), read_trajectory(out / "truth.tum").poses
    camera = DepthCamera(**info["camera"])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(room_mesh(1, hall=True)))
    k = camera.fx * camera.baseline / camera.disparity_step
    for i in range(4):
        points = scans[i].points.astype(np.float64)
        depth = points[:, 2]
        assert np.percentile(depth, 90) > 6.0 and depth.max() < camera.max_depth + 0.5  # far, to 8 m + noise
        far = depth > 5.0  # millimetre depths on the disparity steps beyond 5 m
        assert np.abs(k / depth[far] - np.rint(k / depth[far])).max() < 0.02
        gap = scene.compute_distance(o3d.core.Tensor(se3.transform_points(truth[i], points).astype(np.float32)))
        assert np.mean(gap.numpy() < 4 * camera.sigma(depth) + depth**2 / k / 2 + 0.001) > 0.99
        # 5 cm lower (camera y points down) and 1 degree off, the near points (within 3 m: 1-13 mm of noise) leave
        # the surfaces
        near = depth < 3.0
        moved = truth[i] @ se3.from_xyz_euler(np.array([[0, 0.05, 0, 0, 0, np.radians(1.0)]]))[0]
        far_off = scene.compute_distance(o3d.core.Tensor(se3.transform_points(moved, points[near]).astype(np.float32)))
        assert np.median(far_off.numpy()) > 3 * np.median(gap.numpy()[near])


def test_a_path_of_another_scene_is_refused(tmp_path):
    result = invoke(["simulate", "--scene", "room", "--path", "loop", "-n", "3", "-o", str(tmp_path / "r")])
    assert result.exit_code == 2 and "a room has walk, rpy, across, hall" in result.output
    result = invoke(["simulate", "--path", "rpy", "-n", "3", "-o", str(tmp_path / "s")])
    assert result.exit_code == 2 and "a street has loop or eight" in result.output
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").glob("frame-*"))


def test_refine_from_the_true_poses_of_a_depth_camera_stays_at_them(tmp_path):
    sim = tmp_path / "room"
    assert invoke(["simulate", "--scene", "room", "-n", "90", "--seed", "3", "-o", str(sim), "-q"]).exit_code == 0
    reports = {}
    weigh = tmp_path / "weigh.yaml"  # from the truth, with the cells weighed by the measured range noise
    weigh.write_text("optimiser:\n  dense_depth_noise: true\n")
    for start in ("truth.tum", "warm_start.tum"):
        run = tmp_path / start
        extra = ["-c", str(weigh)] if start == "truth.tum" else []
        result = invoke(["refine", "-s", str(sim), "-p", str(sim / start), "--gt", str(sim / "truth.tum"), "-o",
                         str(run), "-q", *extra])
        assert result.exit_code == 0, result.output
        reports[start] = json.loads((run / "report.json").read_text())
    truth, drifted = reports["truth.tum"], reports["warm_start.tum"]
    noise = truth["start"]["dense"]["depth_noise"]  # measured on the frames, and the cells weighed by it
    assert noise["frames"] == 20 and noise["quartic_m2_per_m4"] > 0.0
    assert drifted["start"]["dense"]["depth_noise"] is None  # off by default
    assert truth["metrics"]["ape_trans_rmse_m"] < 0.003  # (2.7 m median depth: 1.2-20 mm of noise a point)
    assert truth["metrics"]["rpe_rot_rmse_deg"] < 0.03
    # from the visual odometry (drifting 0.15 deg a frame in rotation), a map as sharp as the truth's; on a path
    # this short (0.3 m) the SE(3) alignment of APE leaves the rotation free, so the steps and the map judge
    sharpest = truth["warm_start_metrics"]["map_entropy"]
    assert drifted["metrics"]["map_entropy"] < sharpest + 0.02 < drifted["warm_start_metrics"]["map_entropy"]
    assert drifted["metrics"]["rpe_rot_rmse_deg"] < 0.6 * drifted["warm_start_metrics"]["rpe_rot_rmse_deg"]
