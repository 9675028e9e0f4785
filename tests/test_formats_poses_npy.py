"""dm2's own ``poses.npy`` (N x 4 x 4): read by ``dm2 info`` / ``dm2 eval`` as the "npy" trajectory format."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shared_helpers import assert_one_line_error, run

from dm2_backend.formats import detect_trajectory_format, read_trajectory, write_trajectory
from dm2_backend.formats.dm2_priors import write_init_pose
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.outputs import write_trajectories
from dm2_backend.runtime.errors import InputError


def poses(n: int = 20, planar: bool = False) -> np.ndarray:
    rng = np.random.default_rng(1)
    if planar:
        return se3.from_xy_yaw(np.column_stack([rng.normal(0, 5, (n, 2)), rng.uniform(-3, 3, n)]))
    return se3.make_poses(Rotation.random(n, random_state=2).as_matrix(), rng.normal(0, 5, (n, 3)))


@pytest.mark.parametrize("planar", [False, True])
def test_info_reads_the_poses_npy_of_a_run_folder(tmp_path, planar):
    T = poses(planar=planar)
    write_trajectories(tmp_path, Trajectory(T, np.arange(len(T)) * 0.1, planar=planar), None, None)
    path = tmp_path / "poses.npy"
    assert detect_trajectory_format(path) == "npy"
    traj = read_trajectory(path)
    np.testing.assert_array_equal(traj.poses, T)
    assert traj.planar == planar and traj.timestamps is None
    result = run("info", str(path))
    assert result.exit_code == 0, result.output
    assert "npy" in result.output and "20" in result.output
    assert ("yes (2D)" if planar else "no (3D)") in result.output


def test_write_read_round_trip_and_init_pose_is_still_dm2(tmp_path):
    T = poses()
    write_trajectory(Trajectory(T), tmp_path / "copy.npy", "npy")
    np.testing.assert_array_equal(read_trajectory(tmp_path / "copy.npy").poses, T)
    write_init_pose(T, tmp_path / "init_pose.npy")
    assert detect_trajectory_format(tmp_path / "init_pose.npy") == "dm2"


@pytest.mark.parametrize(
    "array, problem",
    [
        (np.zeros((3, 4, 3)), "expected (N, 4, 4)"),
        (np.tile(np.eye(4), (2, 1, 1)) * [1, 1, 1, 2], "bottom row"),
        (np.array([np.eye(4), np.full((4, 4), np.nan)]), "pose 1 has NaN"),
        (np.array([np.eye(4), np.diag([2.0, 1, 1, 1])]), "pose 1"),
    ],
)
def test_bad_arrays_are_one_line(tmp_path, array, problem):
    path = tmp_path / "bad.npy"
    np.save(path, array)
    with pytest.raises(InputError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        read_trajectory(path, "npy")
    assert_one_line_error(run("info", str(path), "--format", "npy"), "bad.npy")


def test_pickled_arrays_are_refused(tmp_path):
    path = tmp_path / "pickled.npy"
    np.save(path, np.array([{"pose": np.eye(4)}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="numeric|unpickled"):
        read_trajectory(path, "npy")
