"""CARMEN ROBOTLASER1 by hand: field order (laser pose, then robot pose, then tv rv safety distances and
turn axis, then the ipc and logger timestamps), and the laser-to-robot offset the messages imply when the
log has no front-laser PARAMs, so that scans are matched in the robot frame and the laser pose is written."""

from __future__ import annotations

import math

import numpy as np

from dm2_backend.formats.carmen import laser_offset, load, open_carmen_scans, read_carmen, write_carmen
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory

#: robot poses and the laser 0.3 m ahead of the axle, 0.05 m to the left, turned 0.02 rad
OFFSET = (0.3, 0.05, 0.02)
ROBOT = [(1.0, 2.0, math.pi / 2), (1.5, 2.5, 1.0)]


def robotlaser(robot, t: float) -> str:
    laser = se3.to_xy_yaw(se3.from_xy_yaw(np.array([robot])) @ se3.from_xy_yaw(np.array([OFFSET])))[0]
    ranges = "1.000 2.000 3.000"
    # laser_type start_angle fov angular_resolution maximum_range accuracy remission_mode
    head = "ROBOTLASER1 0 -0.100000 0.200000 0.100000 81.900000 0.010000 0"
    pose = " ".join(f"{v:.6f}" for v in (*laser, *robot))
    # n ranges, m remissions, laser pose, robot pose, tv rv forward_safety side_safety turn_axis, ipc host logger
    return f"{head} 3 {ranges} 0 {pose} 0.100000 0.000000 0.550000 0.050000 1000000.000000 {t!r} host {t - 100:.6f}"


def write_log(path):
    path.write_text("\n".join(robotlaser(r, 100.0 + k) for k, r in enumerate(ROBOT)) + "\n")
    return path


def test_robotlaser1_fields_and_offset(tmp_path):
    path = write_log(tmp_path / "hand.log")
    log = load(path)
    msg = log.messages["ROBOTLASER1"][0]
    assert msg.timestamp == 100.0 and msg.logger_timestamp == 0.0 and msg.host == "host"
    assert msg.start_angle == -0.1 and math.isclose(msg.angular_resolution, 0.1)
    np.testing.assert_allclose(msg.robot_pose, ROBOT[0], atol=1e-6)
    np.testing.assert_allclose(laser_offset(log, "ROBOTLASER1"), OFFSET, atol=2e-6)
    seq = open_carmen_scans(path)
    # both trajectories are robot poses: the odometry field, and the laser field moved back by the offset
    for name in ("odometry", "logged"):
        np.testing.assert_allclose(se3.to_xy_yaw(seq.trajectories[name].poses), ROBOT, atol=2e-6)
    np.testing.assert_allclose(seq.timestamps, [100.0, 101.0])
    # scans in the robot frame: beam k at start + k * step from the laser, the laser at OFFSET
    a = -0.1 + 0.1 * np.arange(3) + OFFSET[2]
    r = np.array([1.0, 2.0, 3.0])
    expected = np.column_stack([r * np.cos(a) + OFFSET[0], r * np.sin(a) + OFFSET[1], np.zeros(3)])
    np.testing.assert_allclose(seq[0].points, expected, atol=1e-5)
    # the same world points whichever pose is used: laser pose + raw beams == robot pose + robot-frame points
    laser_world = se3.from_xy_yaw(np.array([msg.laser_pose]))[0]
    raw = np.column_stack([r * np.cos(a - OFFSET[2]), r * np.sin(a - OFFSET[2]), np.zeros(3)])
    np.testing.assert_allclose(se3.transform_points(laser_world, raw),
                               se3.transform_points(seq.trajectories["odometry"].poses[0], expected), atol=1e-5)


def test_robotlaser1_writes_the_laser_pose(tmp_path):
    path = write_log(tmp_path / "hand.log")
    moved = se3.from_xy_yaw(np.array([[2.0, 3.0, 0.5], [2.5, 3.5, 0.6]]))  # refined robot poses
    out = tmp_path / "out.log"
    write_carmen(out, Trajectory(moved, np.array([100.0, 101.0]), planar=True), path)
    text = out.read_text()
    assert "PARAM robot_frontlaser_offset 0.3" in text  # the derived offset is written down
    words = next(line for line in text.split("\n") if line.startswith("ROBOTLASER1")).split()
    laser = se3.to_xy_yaw(moved[:1] @ se3.from_xy_yaw(np.array([OFFSET])))[0]
    p = 10 + 3 + 0  # the laser pose follows the ranges and the (empty) remissions
    np.testing.assert_allclose([float(w) for w in words[p:p + 3]], laser, atol=2e-6)
    back = read_carmen(out)
    np.testing.assert_allclose(se3.to_xy_yaw(back.poses), se3.to_xy_yaw(moved), atol=2e-6)


def test_robotlaser1_inconsistent_poses_keep_no_offset(tmp_path):
    """A laser pose from another estimator (corrected) than the robot pose: no constant offset to derive."""
    lines = [robotlaser(ROBOT[0], 100.0), robotlaser(ROBOT[1], 101.0)]
    words = lines[1].split()
    words[13] = f"{float(words[13]) + 0.4:.6f}"  # the second laser x moved 0.4 m
    (tmp_path / "c.log").write_text(lines[0] + "\n" + " ".join(words) + "\n")
    assert laser_offset(load(tmp_path / "c.log"), "ROBOTLASER1") == (0.0, 0.0, 0.0)
    assert laser_offset(load(tmp_path / "c.log"), "ROBOTLASER1", ReadOptions(laser_offset=OFFSET)) == OFFSET
