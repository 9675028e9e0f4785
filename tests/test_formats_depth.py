"""Depth image sequences (7-Scenes, TUM RGB-D layouts) back-projected to scans."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from shared_helpers import DATA, need

from dm2_backend.cli.main import cli
from dm2_backend.formats import (
    ReadOptions,
    detect_scan_source,
    detect_trajectory_format,
    open_scans,
    read_trajectory,
)
from dm2_backend.formats.depth import back_project, read_depth_image, read_depth_list
from dm2_backend.kernel.geometry import se3
from dm2_backend.runtime.errors import InputError

KITCHEN = DATA / "depth3d" / "redkitchen_000-499"
K585 = (585.0, 585.0, 320.0, 240.0)


def save_png(path: Path, depth: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(depth.astype(np.uint16)).save(path)


def plane_depth(normal, offset, intrinsics, scale, shape=(48, 64)) -> np.ndarray:
    """Depth image (units of 1/scale m) of the plane n.X = offset seen by a pinhole camera."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    z = offset / (rays @ np.asarray(normal, dtype=np.float64))
    return np.round(z * scale)


# ---------------------------------------------------------------- back-projection


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_plane_back_projects_onto_plane(stride):
    intr = (50.0, 55.0, 31.5, 23.5)
    normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    depth = plane_depth(normal, 2.0, intr, 1000.0)
    depth[5, ::4] = 0  # invalid pixels
    depth[10, 0] = 65535
    pts = back_project(depth.astype(np.uint16), intr, 1000.0, stride)
    sub = depth[::stride, ::stride]
    assert len(pts) == ((sub > 0) & (sub < 65535)).sum()
    assert np.abs(pts.astype(np.float64) @ normal - 2.0).max() < 1e-3  # mm quantisation
    assert (pts[:, 2] > 0).all()


def test_back_projection_matches_open3d():
    path = need(KITCHEN / "frame-000123.depth.png")
    depth = read_depth_image(path)
    assert depth.shape == (480, 640) and depth.dtype == np.uint16
    ours = back_project(depth, K585, 1000.0, 2)
    cam = o3d.camera.PinholeCameraIntrinsic(640, 480, *K585)
    ref = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(depth), cam, depth_scale=1000.0, depth_trunc=1e6, stride=2)
    np.testing.assert_allclose(ours, np.asarray(ref.points), atol=1e-5)


# ---------------------------------------------------------------- 7-Scenes (real)


def test_seven_scenes_real():
    folder = need(KITCHEN)
    assert detect_scan_source(folder) == "depth" and detect_trajectory_format(folder) == "depth"
    seq = open_scans(folder)
    assert len(seq) == 500 and seq.meta["layout"] == "7-scenes" and seq.meta["depth_scale"] == 1000.0
    np.testing.assert_allclose(seq.timestamps, np.arange(500) / 30.0)
    ref = seq.trajectories["reference"]
    for i in (0, 250, 499):
        raw = np.loadtxt(folder / f"frame-{i:06d}.pose.txt")
        np.testing.assert_array_equal(ref.poses[i][:3, 3], raw[:3, 3])
        np.testing.assert_allclose(ref.poses[i], raw, atol=1e-3)  # rotations snapped to SO(3)
    assert se3.rotation_error(ref.poses[:, :3, :3]).max() < 1e-9  # valid for evo
    traj = read_trajectory(folder)
    np.testing.assert_array_equal(traj.poses, ref.poses)
    assert 3.5 < traj.path_length < 4.5
    scan = seq[42]
    assert 40000 < len(scan) <= 320 * 240 and scan.timestamp == pytest.approx(42 / 30)
    assert scan.points[:, 2].min() > 0.3 and scan.points[:, 2].max() < 10
    full = open_scans(folder, options=ReadOptions(stride=1))[42]
    assert len(full) > 3.5 * len(scan)


def test_seven_scenes_frame_is_fast():
    seq = open_scans(need(KITCHEN))
    seq[0]
    times = []
    for i in range(1, 8):
        t = time.perf_counter()
        seq[i]
        times.append(time.perf_counter() - t)
    assert np.median(times) < 0.05


def test_depth_scale_option_overrides():
    folder = need(KITCHEN)
    a = open_scans(folder)[7]
    b = open_scans(folder, options=ReadOptions(depth_scale=2000.0))[7]
    np.testing.assert_allclose(b.points, a.points / 2, rtol=1e-6)


def test_cli_info_depth():
    folder = need(KITCHEN)
    result = CliRunner().invoke(cli, ["info", str(folder)])
    assert result.exit_code == 0, result.output
    assert "7-scenes" in result.output and "poses 'reference'  500" in result.output


# ---------------------------------------------------------------- 7-Scenes (synthetic, bad input)


def seven_scenes(tmp_path: Path, n: int = 3) -> Path:
    for i in range(n):
        depth = plane_depth([0, 0, 1], 1.0 + 0.1 * i, K585, 1000.0, (480, 640))
        save_png(tmp_path / f"frame-{i:06d}.depth.png", depth)
        pose = se3.from_xyz_euler(np.array([0.1 * i, 0, 0, 0, 0, 0.05 * i]))
        np.savetxt(tmp_path / f"frame-{i:06d}.pose.txt", pose)
    return tmp_path


def test_seven_scenes_synthetic(tmp_path):
    folder = seven_scenes(tmp_path)
    seq = open_scans(folder)
    assert seq.meta["intrinsics"] == K585  # the dataset default without camera-intrinsics.txt
    np.testing.assert_allclose(seq[2].points[:, 2], 1.2, atol=1e-6)
    (folder / "camera-intrinsics.txt").write_text("500 0 320\n0 500 240\n0 0 1\n")
    assert open_scans(folder).meta["intrinsics"] == (500.0, 500.0, 320.0, 240.0)


def test_seven_scenes_bad_inputs(tmp_path):
    folder = seven_scenes(tmp_path)
    (folder / "frame-000001.pose.txt").unlink()
    with pytest.raises(InputError, match="pose file missing") as exc:
        open_scans(folder)
    assert exc.value.source.endswith("frame-000001.pose.txt")
    np.savetxt(folder / "frame-000001.pose.txt", np.diag([2.0, 1, 1, 1]))
    with pytest.raises(InputError, match="not a rotation") as exc:
        read_trajectory(folder)
    assert exc.value.source.endswith("frame-000001.pose.txt")
    (folder / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1\n")
    with pytest.raises(InputError, match="16 numbers"):
        open_scans(folder)
    np.savetxt(folder / "frame-000001.pose.txt", np.eye(4))
    (folder / "camera-intrinsics.txt").write_text("500 0 320\n0 500 240\n0 1 1\n")
    with pytest.raises(InputError, match="pinhole"):
        open_scans(folder)
    (folder / "camera-intrinsics.txt").unlink()
    save_png(folder / "frame-000002.depth.png", np.zeros((480, 640)))
    with pytest.raises(InputError, match="empty scan") as exc:
        open_scans(folder)[2]
    assert exc.value.source.endswith("frame-000002.depth.png")
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(folder / "frame-000002.depth.png")
    with pytest.raises(InputError, match="16-bit"):
        open_scans(folder)[2]
    with pytest.raises(InputError, match="stride"):
        open_scans(folder, options=ReadOptions(stride=0))


# ---------------------------------------------------------------- TUM RGB-D (synthetic)


def tum_layout(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
    depth_t = 1305031102.0 + np.arange(6) / 30.0 + 0.003
    for k, t in enumerate(depth_t):
        depth = plane_depth([0, 0, 1], 1.0 + k, (525.0, 525.0, 319.5, 239.5), 5000.0, (480, 640))
        save_png(tmp_path / "depth" / f"{t:.6f}.png", depth)
    lines = ["# depth maps", "# timestamp filename"] + [f"{t:.6f} depth/{t:.6f}.png" for t in depth_t]
    (tmp_path / "depth.txt").write_text("\n".join(lines) + "\n")
    gt_t = 1305031102.0 + 0.05 + np.arange(10) / 100.0  # starts after the first frame, ends before the last
    xyz = np.c_[np.arange(10) * 0.01, np.zeros(10), np.zeros(10)]
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (10, 1))
    rows = [" ".join(f"{v:.6f}" for v in (t, *p, *q)) for t, p, q in zip(gt_t, xyz, quat, strict=True)]
    (tmp_path / "groundtruth.txt").write_text("# ground truth\n" + "\n".join(rows) + "\n")
    return tmp_path, depth_t, gt_t, xyz


def test_tum_layout_association(tmp_path):
    folder, depth_t, gt_t, xyz = tum_layout(tmp_path)
    seq = open_scans(folder)
    assert seq.meta["layout"] == "tum" and len(seq) == 6 and seq.meta["depth_scale"] == 5000.0
    np.testing.assert_array_equal(seq.timestamps, [float(f"{t:.6f}") for t in depth_t])
    ref = seq.trajectories["reference"]
    expected = [k for k, t in enumerate(seq.timestamps) if np.abs(gt_t - t).min() <= 0.02]
    assert ref.meta["scan_index"].tolist() == expected == [1, 2, 3, 4]
    for k, i in enumerate(expected):
        j = int(np.argmin(np.abs(gt_t - seq.timestamps[i])))
        np.testing.assert_allclose(ref.poses[k][:3, 3], xyz[j], atol=1e-9)
        assert ref.timestamps[k] == seq.timestamps[i]
    np.testing.assert_allclose(seq[3].points[:, 2], 4.0, atol=1e-3)  # factor 5000 per metre
    np.testing.assert_array_equal(read_trajectory(folder, "depth").poses, ref.poses)
    custom = open_scans(folder, options=ReadOptions(intrinsics=(600.0, 600.0, 320.0, 240.0)))
    assert custom.meta["intrinsics"] == (600.0, 600.0, 320.0, 240.0)


def test_tum_bad_depth_list(tmp_path):
    folder, *_ = tum_layout(tmp_path)
    text = (folder / "depth.txt").read_text().splitlines()
    (folder / "depth.txt").write_text("\n".join(text[:3] + [text[5], text[4]] + text[6:]) + "\n")
    with pytest.raises(InputError, match="unsorted") as exc:
        open_scans(folder)
    assert exc.value.line == 5
    (folder / "depth.txt").write_text("\n".join(text[:3] + ["1305031102.5"] + text[4:]) + "\n")
    with pytest.raises(InputError, match="timestamp filename") as exc:
        open_scans(folder)
    assert exc.value.line == 4
    result = CliRunner().invoke(cli, ["info", str(folder)])
    assert result.exit_code == 2 and result.stderr.strip().endswith("expected 'timestamp filename', got "
                                                                     "'1305031102.5'")
    assert str(folder / "depth.txt") + ":4:" in result.stderr and result.stderr.strip().count("\n") == 0
    (folder / "depth.txt").write_text("\n".join(text) + "\n1305031109.0 depth/missing.png\n")
    with pytest.raises(InputError, match="no such file") as exc:
        open_scans(folder)[6]
    assert exc.value.source.endswith("missing.png")
    (folder / "groundtruth.txt").unlink()
    with pytest.raises(InputError, match="no reference poses"):
        read_trajectory(folder, "depth")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(0, 2e9, allow_nan=False), min_size=1, max_size=15, unique=True),
       st.sampled_from([" ", "\t", "   "]))
def test_depth_list_property(tmp_path, stamps, sep):
    stamps = sorted(stamps)
    names = [f"depth/{k}.png" for k in range(len(stamps))]
    path = tmp_path / "depth.txt"
    path.write_text("# comment\n" + "".join(f"{t!r}{sep}{n}\n" for t, n in zip(stamps, names, strict=True)))
    got, got_names = read_depth_list(path)
    np.testing.assert_array_equal(got, stamps)
    assert got_names == names


def test_the_depth_camera_in_use_is_stated_and_defaults_are_named(tmp_path, caplog):
    """Intrinsics and depth scale are logged as read, with where each came from; a default assumed gets a line of
    its own; the run folder's config.yaml states them (comments) after the config it can read back."""
    import logging

    import yaml

    from dm2_backend import config
    from dm2_backend.pipeline.inputs import depth_sensor, log_sensor
    from dm2_backend.pipeline.run_writer import sensor_comment

    folder = seven_scenes(tmp_path / "seq")
    assumed = depth_sensor(open_scans(folder))
    assert assumed["intrinsics"] == {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0}
    assert assumed["depth_scale"] == 1000.0 and assumed["assumed"] == ["intrinsics", "depth_scale"]
    with caplog.at_level(logging.INFO, logger="dm2_backend.pipeline.inputs"):
        log_sensor(assumed)
    lines = [r.getMessage() for r in caplog.records]
    assert "fx 585 fy 585 cx 320 cy 240 (7-Scenes default)" in lines[0] and "1000 units per metre (7-Scenes" in lines[0]
    assert len(lines) == 2 and "intrinsics and depth scale assumed" in lines[1]  # flat walls: no noise to state
    (folder / "camera-intrinsics.txt").write_text("500 0 320\n0 500 240\n0 0 1\n")
    given = depth_sensor(open_scans(folder, options=ReadOptions(depth_scale=5000.0)))
    assert given["from"] == {"intrinsics": "camera-intrinsics.txt", "depth_scale": "--depth-scale"}
    assert given["assumed"] == [] and given["intrinsics"]["fx"] == 500.0
    path = tmp_path / "config.yaml"
    config.dump(config.load(None), path, footer=sensor_comment(given))
    assert "fx 500 fy 500 cx 320 cy 240 (camera-intrinsics.txt); depth scale 5000" in path.read_text()
    assert config.load(path) == config.load(None) and yaml.safe_load(path.read_text())["seed"] == 0
