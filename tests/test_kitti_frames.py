"""KITTI camera-frame poses through a run: ``calib.txt`` beside the inputs is found and announced, outputs go
back to the camera frame (LiDAR-frame copies named as such), and camera-frame poses meeting LiDAR scans with
no calibration get a warning."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case
from scipy.spatial.transform import Rotation
from shared_helpers import DATA, need

from dm2_backend.cli.main import cli
from dm2_backend.formats import read_trajectory, write_trajectory
from dm2_backend.formats.kitti import camera_to_lidar, find_calib, lidar_to_camera, looks_camera_frame, read_calib_tr
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.simulate.sequence import write_sequence

#: KITTI's velodyne -> camera rotation (x forward, z up -> z forward, y down) with a small offset
TR = se3.make_poses(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), [0.03, -0.07, -0.27])


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def write_calib(path: Path, Tr: np.ndarray = TR) -> Path:
    row = " ".join(f"{v:.12e}" for v in Tr[:3, :].reshape(12))
    path.write_text(f"P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: {row}\n")
    return path


@pytest.fixture(scope="module")
def kitti_layout(tmp_path_factory) -> Path:
    """The KITTI odometry layout: sequences/00/{velodyne/, times.txt, calib.txt} and poses/00.txt (camera frame)."""
    case = planar_case()
    root = tmp_path_factory.mktemp("kitti")
    seq = root / "sequences" / "00"
    write_sequence(seq, case.scans, case.gt, case.warm, 10.0)
    write_calib(seq / "calib.txt")
    (root / "poses").mkdir()
    for name, poses in (("00.txt", case.warm), ("00_gt.txt", case.gt)):
        write_trajectory(Trajectory(lidar_to_camera(poses, TR)), root / "poses" / name, "kitti")
    (seq / "config.yaml").write_text(yaml.safe_dump({"seed": 1, "frames": {"max_points": 128}, "optimiser": {
        "points_per_frame": 32, "bce_points_per_frame": 16, "batch_groups": 16, "grid_max_cells": 2**12}}))
    return root


def test_calib_is_found_beside_the_scans_or_the_poses(kitti_layout, tmp_path):
    seq = kitti_layout / "sequences" / "00"
    assert find_calib(kitti_layout / "poses" / "00.txt", seq / "velodyne") == seq / "calib.txt"
    assert find_calib(seq) == seq / "calib.txt"
    assert find_calib(kitti_layout / "poses" / "00.txt") is None
    (tmp_path / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")  # no Tr line: not a LiDAR calibration
    assert find_calib(tmp_path) is None


def test_camera_frame_is_recognised_by_the_motion(kitti_layout):
    case = planar_case()
    assert not looks_camera_frame(case.gt) and looks_camera_frame(lidar_to_camera(case.gt, TR))
    straight = se3.make_poses(Rotation.from_euler("z", np.linspace(0, 3, 30)[:, None]).as_matrix(),
                         np.c_[np.linspace(0, 30, 30), np.zeros(30), np.zeros(30)])  # straight along LiDAR x
    assert not looks_camera_frame(straight) and looks_camera_frame(lidar_to_camera(straight, TR))


def test_a_run_on_camera_frame_poses_writes_camera_frame_outputs(kitti_layout, tmp_path):
    seq, poses = kitti_layout / "sequences" / "00", kitti_layout / "poses"
    out = tmp_path / "run"
    result = CliRunner().invoke(cli, ["refine", "--scans", str(seq / "velodyne"), "--poses", str(poses / "00.txt"),
                                      "--gt", str(poses / "00_gt.txt"), "-c", str(seq / "config.yaml"),
                                      "--epochs", "1", "-q", "--no-cache", "--out", str(out)], obj={})
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert f"using {seq / 'calib.txt'}" in result.output
    Tr = read_calib_tr(seq / "calib.txt")
    lidar = read_trajectory(out / "poses_lidar_kitti.txt", "kitti").poses
    camera = read_trajectory(out / "poses_kitti.txt", "kitti").poses
    np.testing.assert_allclose(camera, lidar_to_camera(lidar, Tr), atol=1e-9)
    np.testing.assert_allclose(np.load(out / "poses.npy"), camera, atol=1e-9)
    np.testing.assert_allclose(read_trajectory(out / "poses_tum.txt", "tum").poses, camera, atol=1e-6)
    # the warm start written back in the camera frame is the input file
    given = read_trajectory(poses / "00.txt", "kitti").poses
    np.testing.assert_allclose(read_trajectory(out / "warm_start_kitti.txt", "kitti").poses, given, atol=1e-9)
    # the evaluation in the report is in one frame: the refined camera poses against the camera ground truth
    gt = read_trajectory(poses / "00_gt.txt", "kitti").poses
    report = json.loads((out / "report.json").read_text())
    err = np.linalg.norm(camera_to_lidar(camera, Tr)[:, :3, 3] - camera_to_lidar(gt, Tr)[:, :3, 3], axis=1)
    assert report["metrics"]["ape_trans_rmse_m"] <= float(np.sqrt(np.mean(err**2))) + 1e-9


def test_camera_frame_poses_without_calibration_warn(tmp_path):
    folder = need(DATA / "lidar3d" / "kitti00")
    scans = tmp_path / "velodyne"
    scans.mkdir()
    for f in sorted(folder.glob("*.bin")):
        (scans / f.name).symlink_to(f)
    gt = tmp_path / "gt.txt"
    gt.write_text((folder / "poses_gt.txt").read_text())
    result = CliRunner().invoke(cli, ["refine", "--scans", str(scans), "--warm-start", "icp", "--gt", str(gt),
                                      "--epochs", "1", "-q", "--no-cache", "--out", str(tmp_path / "run")], obj={})
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "look camera-frame" in result.output and "--calib" in result.output
