"""KITTI raw drives: OXTS poses equal pykitti's, LiDAR frame through the calibration, Velodyne scans and
stamps, detection, the gps topology, one-line errors for bad input, ``dm2 info`` / ``dm2 convert``.

Every drive is generated here in the published text and binary layout (no KITTI data needed)."""

from __future__ import annotations

import calendar
import datetime as dt
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from shared_helpers import assert_one_line_error, run

from dm2_backend.formats import ReadOptions, detect_scan_source, detect_trajectory_format, open_scans, read_trajectory
from dm2_backend.formats.kitti_raw import oxts_poses, parse_stamp, read_drive, read_oxts_file
from dm2_backend.formats.scan_folder import write_bin
from dm2_backend.formats.tum import read_tum
from dm2_backend.kernel.prepared import Frames
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.plugins.topology_poses import GpsTopology
from dm2_backend.plugins.topology_radius import RadiusTopology
from dm2_backend.runtime.errors import InputError


def _import_pykitti():
    """pykitti 0.3.1's ``__init__`` imports its tracking module, which imports ``cv2`` (undeclared, and unused
    by ``raw`` and ``utils``); without OpenCV a placeholder stands in for that one import."""
    try:
        import pykitti
    except ModuleNotFoundError as exc:
        if exc.name == "pykitti":
            pytest.skip("pykitti is the reference (pip install -e '.[dev]')", allow_module_level=True)
        if exc.name != "cv2":
            raise
        sys.modules["cv2"] = types.ModuleType("cv2")
        try:
            import pykitti
        finally:
            del sys.modules["cv2"]
    return pykitti


pykitti = _import_pykitti()

DATE, DRIVE = "2011_09_26", "0018"
START = dt.datetime(2011, 9, 26, 13, 2, 25)


def stamp_text(seconds: float) -> str:
    """KITTI's 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn' for START + seconds."""
    ns = round(seconds * 1e9)
    t = START + dt.timedelta(microseconds=ns // 1000)
    return t.strftime("%Y-%m-%d %H:%M:%S.") + f"{t.microsecond:06d}{ns % 1000:03d}"


def epoch(seconds: float) -> float:
    return calendar.timegm(START.timetuple()) + seconds


def rigid_calib(path: Path, R: np.ndarray, t: np.ndarray, extra: str = "") -> None:
    """A KITTI rigid calibration file, printed at full precision."""
    path.write_text("calib_time: 25-May-2012 16:47:16\n"
                    f"R: {' '.join(map(repr, R.reshape(-1).tolist()))}\nT: {' '.join(map(repr, t.tolist()))}\n"
                    + extra)


def make_drive(base: Path, n: int = 12, *, imu_yaw: float = 0.3, straight: bool = False, seed: int = 0) -> Path:
    """A synced drive in the published layout: a loop of radius 15 m (or a straight eastward line)."""
    rng = np.random.default_rng(seed)
    date = base / DATE
    drive = date / f"{DATE}_drive_{DRIVE}_sync"
    for sub in ("oxts/data", "velodyne_points/data"):
        (drive / sub).mkdir(parents=True)
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    east, north = (np.arange(n) * 1.0, np.zeros(n)) if straight else (15 * np.sin(angle), 15 - 15 * np.cos(angle))
    lat0, lon0 = 49.011212804408, 8.4228850417969
    lat = lat0 + np.degrees(north / 6378137.0)
    lon = lon0 + np.degrees(east / (6378137.0 * np.cos(np.radians(lat0))))
    for i in range(n):
        rpy = [0.0, 0.0, 0.0] if straight else [*rng.normal(0, 0.02, 2), angle[i]]
        floats = [lat[i], lon[i], 116.4 + 0.1 * i, *rpy, *rng.normal(0, 1, 17), 0.1, 0.05]
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(
            " ".join(repr(float(v)) for v in floats) + " 4 10 4 4 6\n")
        write_bin(drive / "velodyne_points" / "data" / f"{i:010d}.bin", rng.uniform(-20, 20, (50 + i, 3)),
                  rng.uniform(0, 1, 50 + i))
    (drive / "oxts" / "timestamps.txt").write_text("".join(stamp_text(0.1 * i) + "\n" for i in range(n)))
    (drive / "velodyne_points" / "timestamps.txt").write_text(
        "".join(stamp_text(0.1 * i + 0.003) + "\n" for i in range(n)))
    R_velo_imu = Rotation.from_euler("xyz", [0.01, -0.02, imu_yaw]).as_matrix()
    rigid_calib(date / "calib_imu_to_velo.txt", R_velo_imu, np.array([-0.808675900, 0.319555900, -0.799723100]))
    rigid_calib(date / "calib_velo_to_cam.txt", Rotation.from_euler("xyz", [-1.57, 0, -1.57]).as_matrix(),
                np.array([-0.004, -0.076, -0.27]), "delta_f: 0 0\ndelta_c: 0 0\n")
    P = "721.5 0 609.6 {} 0 721.5 172.9 0 0 0 1 0"
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\n"
        + "".join(f"R_rect_0{k}: 1 0 0 0 1 0 0 0 1\nP_rect_0{k}: {P.format(-386.1 * (k % 2))}\n" for k in range(4)))
    return drive


@pytest.fixture
def drive(tmp_path) -> Path:
    return make_drive(tmp_path)


def reference(drive: Path):
    return pykitti.raw(str(drive.parents[1]), DATE, DRIVE)


def test_poses_equal_pykitti_in_the_lidar_frame(drive):
    assert detect_trajectory_format(drive) == "kitti-raw"
    ours = read_trajectory(drive)
    ref = reference(drive)
    T_w_imu = np.array([o.T_w_imu for o in ref.oxts])
    packets = np.array([read_oxts_file(f) for f in sorted((drive / "oxts" / "data").iterdir())])
    np.testing.assert_allclose(oxts_poses(packets), T_w_imu, atol=1e-9, rtol=0)  # the devkit convention itself
    T_w_velo = T_w_imu @ np.linalg.inv(ref.calib.T_velo_imu)
    want = np.linalg.inv(T_w_velo[0]) @ T_w_velo
    np.testing.assert_allclose(ours.poses, want, atol=1e-9, rtol=0)
    np.testing.assert_allclose(ours.poses[0], np.eye(4), atol=1e-12)
    assert ours.meta["frame"] == "lidar" and ours.meta["calib"].endswith("calib_imu_to_velo.txt")


def test_calibration_rotates_the_motion_into_the_lidar_frame(tmp_path):
    """IMU driving straight east 1 m and up 0.1 m a frame, level; the LiDAR sees that motion through R_velo_imu."""
    yaw = np.pi / 2
    ours = read_drive(make_drive(tmp_path, 5, imu_yaw=yaw, straight=True))
    step = ours.poses[1:, :3, 3] - ours.poses[:-1, :3, 3]
    R = Rotation.from_euler("xyz", [0.01, -0.02, yaw]).as_matrix()
    np.testing.assert_allclose(step, np.tile(R @ [1.0, 0, 0.1], (4, 1)), atol=1e-6)
    np.testing.assert_allclose(ours.poses[:, :3, :3], np.tile(np.eye(3), (5, 1, 1)), atol=1e-12)


def test_timestamps_are_the_synced_velodyne_stamps(drive):
    ours = read_trajectory(drive)
    np.testing.assert_allclose(ours.timestamps, [epoch(0.1 * i + 0.003) for i in range(12)], atol=1e-6, rtol=0)
    ref = reference(drive)  # pykitti: OXTS stamps as naive datetimes, truncated to microseconds
    ref_s = [t.replace(tzinfo=dt.timezone.utc).timestamp() for t in ref.timestamps]
    np.testing.assert_allclose(ours.meta["oxts_timestamps"], ref_s, atol=1e-6, rtol=0)


def test_scans_equal_pykitti(drive):
    assert detect_scan_source(drive) == "kitti-raw"
    seq = open_scans(drive)
    ref = reference(drive)
    assert len(seq) == len(ref.velo_files) == 12
    for i in (0, 7, 11):
        np.testing.assert_array_equal(seq[i].points, ref.get_velo(i)[:, :3])
        np.testing.assert_array_equal(seq[i].intensity, ref.get_velo(i)[:, 3])
    np.testing.assert_array_equal(seq.timestamps, read_trajectory(drive).timestamps)
    # the user may point at the drive's sensor folders too
    assert detect_trajectory_format(drive / "oxts") == detect_scan_source(drive / "velodyne_points") == "kitti-raw"


def test_gps_topology_reads_a_drive(drive):
    traj = read_trajectory(drive)
    seq = open_scans(drive)
    frames = Frames(points=[s.points for s in seq], timestamps=seq.timestamps, planar=False)
    drifted = traj.poses.copy()
    drifted[:, 0, 3] += np.linspace(0, 3, len(drifted))
    topo = GpsTopology(path=str(drive), radius=8.0).run(frames, drifted)
    np.testing.assert_array_equal(topo.groups, RadiusTopology(radius=8.0).run(frames, traj.poses).groups)


@settings(max_examples=200, deadline=None)
@given(st.datetimes(min_value=dt.datetime(1971, 1, 1), max_value=dt.datetime(2099, 12, 31)),
       st.integers(0, 999))
def test_stamp_parser_agrees_with_datetime(when, extra_ns):
    text = when.strftime("%Y-%m-%d %H:%M:%S.") + f"{when.microsecond:06d}{extra_ns:03d}"
    want = when.replace(tzinfo=dt.timezone.utc).timestamp() + extra_ns * 1e-9
    assert parse_stamp(text) == pytest.approx(want, abs=1e-6)
    assert parse_stamp(when.strftime("%Y-%m-%d %H:%M:%S")) == calendar.timegm(when.timetuple())


@given(st.text(max_size=40))
def test_stamp_parser_rejects_what_is_not_a_stamp(text):
    value = parse_stamp(text)
    assert value is None or len(text.strip()) >= 19


@pytest.mark.parametrize("text", ["2011-13-26 13:02:25.964389445", "2011-02-30 00:00:00", "2011-09-26 24:00:00",
                                  "2011-09-26 13:02", "2011-09-26 13:02:25.1234567890", "1317042145.9643"])
def test_malformed_stamps(text):
    assert parse_stamp(text) is None


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=30, max_size=30))
def test_oxts_parser_reads_exact_values(tmp_path_factory, values):
    path = tmp_path_factory.mktemp("oxts") / "0000000000.txt"
    path.write_text(" ".join(map(repr, values)) + "\n")
    np.testing.assert_array_equal(read_oxts_file(path), values)


def _break(drive: Path, how: str) -> str:
    """Damage a generated drive; returns the name the error must carry."""
    if how == "stamp":
        path = drive / "velodyne_points" / "timestamps.txt"
        lines = path.read_text().splitlines()
        lines[2] = "2011-09-26 13:02:xx.2"
        path.write_text("\n".join(lines) + "\n")
        return "timestamps.txt:3"
    if how == "oxts":
        path = drive / "oxts" / "data" / "0000000004.txt"
        path.write_text(" ".join(path.read_text().split()[:29]) + "\n")
        return "0000000004.txt:1"
    if how == "oxts-text":
        path = drive / "oxts" / "data" / "0000000005.txt"
        fields = path.read_text().split()
        path.write_text(" ".join(fields[:3] + ["abc"] + fields[4:]) + "\n")
        return "0000000005.txt:1: not a number: 'abc'"
    if how == "count":
        (drive / "velodyne_points" / "data" / "0000000011.bin").unlink()
        return "11 Velodyne scans"
    if how == "stamp-count":
        path = drive / "oxts" / "timestamps.txt"
        path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")
        return "11 timestamps for 12 files"
    if how == "calib":
        (drive.parent / "calib_imu_to_velo.txt").unlink()
        return "calib_imu_to_velo.txt"
    if how == "calib-R":
        path = drive.parent / "calib_imu_to_velo.txt"
        path.write_text(path.read_text().replace("R:", "R: 1"))
        return "calib_imu_to_velo.txt:2"
    raise ValueError(how)


@pytest.mark.parametrize("how", ["stamp", "oxts", "oxts-text", "count", "stamp-count", "calib", "calib-R"])
def test_bad_input_is_one_line_naming_the_file(drive, how):
    name = _break(drive, how)
    with pytest.raises(InputError) as err:
        read_trajectory(drive)
    assert name in str(err.value) and "\n" not in str(err.value)
    assert_one_line_error(run("convert", str(drive), str(drive.parent / "out.txt"), "--to", "tum"), name)


def test_info_and_convert(drive, tmp_path):
    info = run("info", str(drive))
    assert info.exit_code == 0, info.output
    assert "kitti-raw" in info.output and "poses" in info.output and "scans" in info.output
    assert "calib_imu_to_velo.txt" in info.output and "points per scan" in info.output
    out = tmp_path / "gps.txt"
    done = run("convert", str(drive), str(out), "--to", "tum")
    assert done.exit_code == 0, done.output
    back, ours = read_tum(out), read_trajectory(drive)
    np.testing.assert_allclose(back.poses, ours.poses, atol=1e-12)
    np.testing.assert_array_equal(back.timestamps, ours.timestamps)


def test_run_inputs(drive):
    """What ``dm2 refine --scans DRIVE --poses DRIVE --gt DRIVE`` gets: every scan paired with its pose."""
    inputs = load_inputs(drive, None, drive, None, ReadOptions(), gt_path=drive)
    assert len(inputs.scans) == len(inputs.given) == len(inputs.gt) == 12
    np.testing.assert_array_equal(inputs.given.poses, inputs.gt.poses)
