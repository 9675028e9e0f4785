"""KITTI poses: agreement with evo, times, calib (LiDAR frame), exact writer, bad input, CLI."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from shared_helpers import DATA, assert_one_line_error, need, run

from dm2_backend.formats import ReadOptions, detect_trajectory_format, read_trajectory
from dm2_backend.formats.kitti import (
    camera_to_lidar,
    lidar_to_camera,
    read_calib_tr,
    read_kitti,
    read_times,
    write_kitti,
)
from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.errors import InputError

TRAJ = DATA / "trajectories"
KITTI00 = DATA / "lidar3d" / "kitti00"


@pytest.mark.parametrize("name", ["KITTI_00_gt.txt", "KITTI_00_ORB.txt"])
def test_agrees_with_evo(name):
    from evo.tools.file_interface import read_kitti_poses_file

    path = need(TRAJ / name)
    assert detect_trajectory_format(path) == "kitti"
    ours = read_trajectory(path)
    theirs = np.array(read_kitti_poses_file(str(path)).poses_se3)
    assert ours.poses.shape == theirs.shape == (4541, 4, 4)
    np.testing.assert_allclose(ours.poses, theirs, atol=1e-9, rtol=0)
    assert ours.timestamps is None  # KITTI_00_gt_times.txt is not named times.txt


def test_times_option_and_sibling_pickup(tmp_path):
    poses, times = need(TRAJ / "KITTI_00_gt.txt"), need(TRAJ / "KITTI_00_gt_times.txt")
    traj = read_kitti(poses, ReadOptions(times=times))
    np.testing.assert_array_equal(traj.timestamps, np.loadtxt(times))
    # a times.txt next to the poses is picked up only when the counts agree
    shutil.copy(poses, tmp_path / "00.txt")
    shutil.copy(times, tmp_path / "times.txt")
    assert read_kitti(tmp_path / "00.txt").meta["times"] == str(tmp_path / "times.txt")
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    assert read_kitti(tmp_path / "00.txt").timestamps is None
    with pytest.raises(InputError, match="2 times for 4541 poses"):
        read_kitti(tmp_path / "00.txt", ReadOptions(times=tmp_path / "times.txt"))


def test_calib_lidar_frame_round_trip(tmp_path):
    folder = need(KITTI00)
    Tr = read_calib_tr(folder / "calib.txt")
    assert Tr.shape == (4, 4) and se3.rotation_error(Tr[:3, :3]) < 1e-14
    raw = np.eye(4)
    raw[:3] = np.array((folder / "calib.txt").read_text().split()[1:13], float).reshape(3, 4)
    np.testing.assert_allclose(Tr, raw, atol=1e-6)
    cam = read_kitti(folder / "poses_gt.txt")
    lidar = read_kitti(folder / "poses_gt.txt", ReadOptions(calib=folder / "calib.txt"))
    np.testing.assert_allclose(lidar.poses, np.linalg.inv(Tr) @ cam.poses @ Tr, atol=1e-12)
    np.testing.assert_allclose(lidar.poses, np.linalg.inv(raw) @ cam.poses @ raw, atol=1e-6)
    assert lidar.meta["frame"] == "lidar" and len(lidar.timestamps) == 6  # times.txt sits next to the poses
    # the car drives forward: +z in the camera frame, +x in the Velodyne frame
    step = se3.relative(lidar.poses[0], lidar.poses[1])[:3, 3]
    assert step[0] > 0.8 and abs(step[1]) < 0.1 and abs(step[2]) < 0.1
    out = tmp_path / "cam.txt"
    write_kitti(lidar, out, ReadOptions(calib=folder / "calib.txt"))
    np.testing.assert_allclose(read_kitti(out).poses, cam.poses, atol=1e-12)
    np.testing.assert_allclose(lidar_to_camera(camera_to_lidar(cam.poses, Tr), Tr), cam.poses, atol=1e-12)


def test_writer_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    poses = se3.make_poses(Rotation.random(50, random_state=1).as_matrix(), rng.normal(0, 1e3, (50, 3)))
    out = tmp_path / "p.txt"
    write_kitti(read_kitti_like(poses), out)
    np.testing.assert_array_equal(read_kitti(out).poses, poses)


def read_kitti_like(poses):
    from dm2_backend.kernel.trajectory import Trajectory

    return Trajectory(poses=poses)


quat = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
xyz = st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(quat, xyz), min_size=1, max_size=20))
def test_property_write_read(tmp_path_factory, rows):
    q = np.array([r[0] for r in rows])
    poses = se3.from_xyz_quat(np.array([r[1] for r in rows]), q, "xyzw")
    out = tmp_path_factory.mktemp("k") / "p.txt"
    write_kitti(read_kitti_like(poses), out)
    np.testing.assert_array_equal(read_kitti(out).poses, poses)


GOOD = "1 0 0 0 0 1 0 0 0 0 1 0\n"


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (GOOD + "1 0 0 0 0 1 0 0 0 0 1\n", 2, "11 columns, expected 12"),
        (GOOD + "1 0 0 nan 0 1 0 0 0 0 1 0\n", 2, "NaN"),
        (GOOD + "1 0 0 inf 0 1 0 0 0 0 1 0\n", 2, "NaN"),
        (GOOD + "2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "not a rotation"),
        ("# c\n" + GOOD + "1 0 0 x 0 1 0 0 0 0 1 0\n", 3, "not a number"),
        ("1 2 3\n", 1, "3 columns"),
    ],
)
def test_bad_input(tmp_path, text, line, problem):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_kitti(path)
    assert info.value.line == line and info.value.source == str(path)
    assert_one_line_error(run("info", str(path), "--format", "kitti"), "bad.txt")
    out = str(tmp_path / "o.txt")
    assert_one_line_error(run("convert", str(path), out, "--from", "kitti", "--to", "tum"), "bad.txt")


@pytest.mark.parametrize(
    "times, line, problem",
    [("0\n0.2\n0.1\n", 3, "unsorted"), ("0\n0.1\n0.1\n", 3, "duplicate"), ("0\nnan\n0.2\n", 2, "NaN")],
)
def test_bad_times(tmp_path, times, line, problem):
    (tmp_path / "p.txt").write_text(GOOD * 3)
    (tmp_path / "t.txt").write_text(times)
    with pytest.raises(InputError, match=problem) as info:
        # a repeated stamp is refused when asked (kept by default: test_convert_times_file_with_repeated_stamps)
        read_kitti(tmp_path / "p.txt", ReadOptions(times=tmp_path / "t.txt", duplicate_times="error"))
    assert info.value.line == line and info.value.source.endswith("t.txt")
    with pytest.raises(InputError):
        read_times(tmp_path / "t.txt")


def test_missing_and_bad_calib(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_kitti(tmp_path / "nope.txt")
    assert_one_line_error(run("info", str(tmp_path / "nope.txt")), "nope.txt")
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match="no 'Tr:' line"):
        read_calib_tr(tmp_path / "calib.txt")
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\nTr: 1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="11 numbers") as info:
        read_calib_tr(tmp_path / "calib.txt")
    assert info.value.line == 2
    (tmp_path / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 3 0\n")
    with pytest.raises(InputError, match="not a rotation"):
        read_calib_tr(tmp_path / "calib.txt")


def test_cli_convert_kitti_to_tum_with_times(tmp_path):
    poses, times = need(TRAJ / "KITTI_00_gt.txt"), need(TRAJ / "KITTI_00_gt_times.txt")
    out = tmp_path / "gt.tum"
    result = run("convert", str(poses), str(out), "--times", str(times))
    assert result.exit_code == 0, result.output
    tum = read_trajectory(out)
    assert tum.meta["format"] == "tum"
    np.testing.assert_array_equal(tum.timestamps, np.loadtxt(times))
    np.testing.assert_allclose(tum.poses, read_kitti(poses).poses, atol=1e-6)  # file rotations are rounded
    back = tmp_path / "back.kitti"
    assert run("convert", str(out), str(back)).exit_code == 0
    np.testing.assert_allclose(read_trajectory(back).poses, tum.poses, atol=1e-12)


def test_cli_convert_with_calib_and_info(tmp_path):
    folder = need(KITTI00)
    out = tmp_path / "lidar.tum"
    result = run("convert", str(folder / "poses_gt.txt"), str(out), "--from", "kitti",
                 "--calib", str(folder / "calib.txt"))
    assert result.exit_code == 0, result.output
    lidar = read_kitti(folder / "poses_gt.txt", ReadOptions(calib=folder / "calib.txt"))
    np.testing.assert_allclose(read_trajectory(out).poses, lidar.poses, atol=1e-6)  # TUM makes R orthonormal
    info = run("info", str(folder / "poses_gt.txt"), "--format", "kitti")
    assert info.exit_code == 0 and "poses" in info.output and "6" in info.output


def test_sniff_needs_rotations(tmp_path):
    path = tmp_path / "m.txt"
    path.write_text("1 2 3 4 5 6 7 8 9 10 11 12\n")
    with pytest.raises(InputError, match="format"):
        detect_trajectory_format(path)
    path.write_text(GOOD)
    assert detect_trajectory_format(path) == "kitti"
