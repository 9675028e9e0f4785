"""DeepMapping2 prior files: the official conventions, round trips, bad input, the "dm2" format, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from shared_helpers import DATA, assert_one_line_error, run

from dm2_backend.formats import detect_trajectory_format, read_trajectory
from dm2_backend.formats.dm2_priors import (
    read_group_matrix,
    read_init_pose,
    read_pairwise_pose,
    read_priors,
    write_group_matrix,
    write_init_pose,
    write_pairwise_pose,
    write_priors,
)
from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.errors import InputError


def official_euler_to_matrix(e: np.ndarray) -> np.ndarray:
    """pytorch3d ``euler_angles_to_matrix(e, "XYZ")`` as copied into DeepMapping2: Rx(a) @ Ry(b) @ Rz(c)."""
    a, b, c = e
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3.make_poses(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(0, 20, (n, 3)))


def test_euler_convention_matches_official():
    rng = np.random.default_rng(1)
    for e in rng.uniform(-np.pi, np.pi, (50, 3)):
        np.testing.assert_allclose(se3.euler_xyz_to_matrix(e), official_euler_to_matrix(e), atol=1e-14)
    # the official writer is scipy's as_euler("XYZ") (utils.mat2ang_np)
    R = Rotation.random(20, random_state=2).as_matrix()
    official = Rotation.from_matrix(R).as_euler("XYZ")
    np.testing.assert_allclose(se3.matrix_to_euler_xyz(R), official, atol=1e-14)


def test_init_pose_file_layout_and_round_trip(tmp_path):
    poses = random_poses(30)
    path = tmp_path / "init_pose.npy"
    write_init_pose(poses, path)
    raw = np.load(path)
    assert raw.shape == (30, 6)
    np.testing.assert_allclose(raw[:, :3], poses[:, :3, 3])
    for row, T in zip(raw, poses, strict=True):  # p_world = R p + t with the official rotation
        np.testing.assert_allclose(official_euler_to_matrix(row[3:]), T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(read_init_pose(path), poses, atol=1e-12)
    write_init_pose(poses, path, dtype=np.float32)  # what the official pre-processing writes
    assert np.load(path).dtype == np.float32
    np.testing.assert_allclose(read_init_pose(path), poses, atol=1e-4)


def test_group_matrix_anchor_first_and_pads(tmp_path):
    groups = np.array([[1, 2, -1], [0, 2, 3], [3, 1, 0], [2, -1, -1]])
    path = tmp_path / "group_matrix.npy"
    write_group_matrix(groups, path)
    raw = np.load(path)
    np.testing.assert_array_equal(raw[:, 0], np.arange(4))  # the anchor comes first
    np.testing.assert_array_equal(raw[0], [0, 1, 2, 0])  # a pad is the anchor itself
    np.testing.assert_array_equal(read_group_matrix(path), groups)
    np.save(path, raw.astype(np.float64))  # integral floats are accepted
    np.testing.assert_array_equal(read_group_matrix(path), groups)


def test_pairwise_direction_matches_official_compose(tmp_path):
    """File entry = anchor in the neighbour's frame; ``compose_pose_diff``: R_anchor ~ R_j @ R_pairwise."""
    poses = random_poses(5, seed=3)
    groups = np.array([[1, 2], [0, 2], [1, 3], [2, 4], [3, -1]])
    rel = np.zeros((5, 2, 4, 4))
    for i in range(5):
        for n, j in enumerate(groups[i]):
            rel[i, n] = se3.relative(poses[i], poses[j]) if j >= 0 else np.eye(4)
    path = tmp_path / "pairwise_pose.npy"
    write_pairwise_pose(rel, path, valid=groups >= 0)
    raw = np.load(path)
    assert raw.shape == (5, 2, 6) and raw.dtype == np.float32
    for i in range(5):
        for n, j in enumerate(groups[i]):
            if j < 0:
                np.testing.assert_array_equal(raw[i, n], 0)
                continue
            R_pw = official_euler_to_matrix(raw[i, n, 3:].astype(np.float64))
            np.testing.assert_allclose(poses[j, :3, :3] @ R_pw, poses[i, :3, :3], atol=1e-5)
            np.testing.assert_allclose(raw[i, n, :3], se3.relative(poses[j], poses[i])[:3, 3], atol=1e-4)
    np.testing.assert_allclose(read_pairwise_pose(path), rel, atol=1e-4)


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 12), st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_property_priors_round_trip(tmp_path_factory, n, k, seed):
    rng = np.random.default_rng(seed)
    poses = random_poses(n, seed % 1000) * np.array([1, 1, 1, 10.0 ** rng.integers(-2, 4)])[None, None, :]
    poses[:, 3] = [0, 0, 0, 1]
    groups = rng.integers(-1, n, (n, k))
    groups[groups == np.arange(n)[:, None]] = -1
    rel = se3.relative(poses[:, None], poses[np.maximum(groups, 0)])
    rel[groups < 0] = np.eye(4)
    folder = tmp_path_factory.mktemp("prior")
    write_priors(folder, poses, groups, rel)
    p, g, r = read_priors(folder)
    np.testing.assert_allclose(p, poses, atol=1e-9 * max(1.0, np.abs(poses).max()))
    np.testing.assert_array_equal(g, groups)
    np.testing.assert_allclose(r[..., :3, :3], rel[..., :3, :3], atol=2e-6)  # float32 file
    np.testing.assert_allclose(r[..., :3, 3], rel[..., :3, 3], atol=2e-6 * max(1.0, np.abs(rel).max()))


def _save(path: Path, array) -> Path:
    np.save(path, array)
    return path


@pytest.mark.parametrize(
    "reader, array, problem",
    [
        (read_init_pose, np.zeros((4, 7)), r"shape \(4, 7\), expected \(N, 6\)"),
        (read_init_pose, np.array([[0, 0, 0, 0, 0, 0], [0, np.nan, 0, 0, 0, 0]]), "row 1 has NaN"),
        (read_init_pose, np.zeros((0, 6)), "expected"),
        (read_group_matrix, np.array([[0, 1], [0, 1]]), "row 1 starts with 0, expected its anchor 1"),
        (read_group_matrix, np.array([[0, 5], [1, 0]]), "index 5 outside 0..1"),
        (read_group_matrix, np.array([[0, 1.5], [1, 0]]), "non-integer"),
        (read_pairwise_pose, np.zeros((3, 2, 4)), "old x y z yaw layout"),
        (read_pairwise_pose, np.full((3, 2, 6), np.inf), "row 0 has NaN"),
        (read_pairwise_pose, np.array(["a", "b"]), "not a numeric"),
    ],
)
def test_bad_arrays(tmp_path, reader, array, problem):
    path = _save(tmp_path / "bad.npy", array)
    with pytest.raises(InputError, match=problem) as info:
        reader(path)
    assert info.value.source == str(path)


def test_bad_files_and_cli(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_init_pose(tmp_path / "none.npy")
    (tmp_path / "text.npy").write_text("not numpy")
    with pytest.raises(InputError, match="not a readable .npy"):
        read_init_pose(tmp_path / "text.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="not a readable .npy"):
        read_pairwise_pose(tmp_path / "obj.npy")
    nan = _save(tmp_path / "init_pose.npy", np.full((3, 6), np.nan))
    assert_one_line_error(run("info", str(nan), "--format", "dm2"), "init_pose.npy")
    out = str(tmp_path / "o.tum")
    assert_one_line_error(run("convert", str(nan), out, "--from", "dm2"), "init_pose.npy")
    write_init_pose(random_poses(2), tmp_path / "init_pose.npy")
    write_group_matrix(np.array([[1], [0], [0]]), tmp_path / "group_matrix.npy")
    write_pairwise_pose(np.tile(np.eye(4), (3, 1, 1, 1)), tmp_path / "pairwise_pose.npy")
    with pytest.raises(InputError, match="2 poses, 3 groups"):
        read_priors(tmp_path)


def test_dm2_trajectory_format_and_cli(tmp_path):
    kitti = DATA / "lidar3d" / "kitti00" / "poses_gt.txt"
    if not kitti.exists():
        pytest.skip(f"{kitti} absent")
    out = tmp_path / "prior" / "init_pose.npy"
    result = run("convert", str(kitti), str(out), "--from", "kitti")
    assert result.exit_code == 0, result.output
    assert detect_trajectory_format(out) == "dm2"
    np.save(tmp_path / "other.npy", np.zeros((3, 7)))
    with pytest.raises(InputError, match="unknown trajectory format"):
        detect_trajectory_format(tmp_path / "other.npy")
    traj = read_trajectory(out)
    np.testing.assert_allclose(traj.poses, read_trajectory(kitti, "kitti").poses, atol=1e-6)
    write_group_matrix(np.array([[1], [0], [1], [2], [3], [4]]), out.with_name("group_matrix.npy"))
    info = run("info", str(out))
    assert info.exit_code == 0 and "dm2" in info.output and "6 x 2" in info.output
    back = tmp_path / "back.kitti"
    assert run("convert", str(out), str(back)).exit_code == 0
    np.testing.assert_allclose(read_trajectory(back).poses, traj.poses, atol=1e-12)
