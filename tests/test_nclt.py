"""NCLT sessions: the published Velodyne packing (a hand-checked point, byte-exact round trip), microsecond
stamps from the file names, ground truth / odometry CSVs in the Velodyne frame (NaN rows dropped, sampled at
the scan stamps), detection, one-line errors, ``dm2 info`` / ``dm2 convert``.

Every session is generated here in the published layout (no NCLT data needed)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation, Slerp
from shared_helpers import assert_one_line_error, run

from dm2_backend.formats import ReadOptions, detect_scan_source, detect_trajectory_format, open_scans, read_trajectory
from dm2_backend.formats.nclt import (
    T_BODY_VEL,
    read_nclt_bin,
    read_nclt_csv,
    sample_at,
    write_nclt_bin,
    write_nclt_csv,
)
from dm2_backend.formats.tum import read_tum
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.runtime.errors import InputError

DATE = "2012-01-08"
UTIME0 = 1326030975726043  # first scan, microseconds


def rz(a):
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def ry(a):
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def rx(a):
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def pose(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """NCLT's ssc_to_homo: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = rz(yaw) @ ry(pitch) @ rx(roll)
    T[:3, 3] = x, y, z
    return T


#: the published x_body_vel, degrees to radians by hand
BODY_VEL = pose(0.002, -0.004, -0.957, *np.radians([0.807, 0.166, -90.703]))


def body(t: float) -> list[float]:
    """The simulated body pose at t seconds after the first scan: level, yaw linear in time."""
    return [2.0 * t, -1.0 + 0.5 * t, 0.3, 0.0, 0.0, 0.2 * t - 1.0]


def pack(values) -> bytes:
    """Points as the published packing, written by hand: <HHHBB per point."""
    return b"".join(struct.pack("<HHHBB", *v) for v in values)


def csv_rows(path: Path, stamps_s: np.ndarray, nan_rows: int = 0) -> None:
    lines = [f"{UTIME0 + round(t * 1e6)}," + ",".join(repr(float(v)) for v in body(t)) for t in stamps_s]
    for i in range(nan_rows):
        lines[i] = lines[i].split(",")[0] + ",nan" * 6
    path.write_text("\n".join(lines) + "\n")


def make_session(base: Path, n: int = 10, gt_start: float = -0.05, nan_rows: int = 2) -> Path:
    """velodyne_sync at 10 Hz, ground truth at 20 Hz in the parent (as downloaded), odometry at 100 Hz."""
    session = base / DATE
    (session / "velodyne_sync").mkdir(parents=True)
    rng = np.random.default_rng(1)
    for i in range(n):
        v = rng.integers(0, 65536, (40 + i, 3))
        rows = [(*p, int(rng.integers(0, 256)), int(rng.integers(0, 32))) for p in v.tolist()]
        (session / "velodyne_sync" / f"{UTIME0 + 100_000 * i}.bin").write_bytes(pack(rows))
    end = 0.1 * (n - 1) + 0.2
    csv_rows(base / f"groundtruth_{DATE}.csv", np.arange(gt_start - 0.05 * nan_rows, end, 0.05), nan_rows)
    csv_rows(session / "odometry_mu_100hz.csv", np.arange(-0.2, end, 0.01))
    return session


@pytest.fixture
def session(tmp_path) -> Path:
    return make_session(tmp_path)


def test_hand_checked_points(tmp_path):
    path = tmp_path / "1326030975726043.bin"
    path.write_bytes(pack([(20000, 20001, 0, 7, 31), (65535, 12345, 20200, 255, 0)]))
    scan = read_nclt_bin(path)
    # x = v * 0.005 - 100: 20000 -> 0, 20001 -> 0.005, 0 -> -100, 65535 -> 227.675, 12345 -> -38.275, 20200 -> 1
    np.testing.assert_allclose(scan.points, [[0.0, 0.005, -100.0], [227.675, -38.275, 1.0]], atol=1e-5)
    np.testing.assert_array_equal(scan.intensity, [7, 255])
    np.testing.assert_array_equal(scan.ring, [31, 0])


@settings(max_examples=50, deadline=None)
@given(hnp.arrays(np.uint16, st.tuples(st.integers(1, 50), st.just(3))),
       hnp.arrays(np.uint8, 50), hnp.arrays(np.uint8, 50))
def test_packing_round_trips_byte_for_byte(tmp_path_factory, counts, intensity, laser):
    m = len(counts)
    path = tmp_path_factory.mktemp("vel") / "a.bin"
    path.write_bytes(pack([(*c, i, lid) for c, i, lid in zip(counts.tolist(), intensity[:m], laser[:m])]))
    scan = read_nclt_bin(path)
    np.testing.assert_allclose(scan.points, counts * 0.005 - 100.0, atol=2e-5)
    again = path.with_name("b.bin")
    write_nclt_bin(again, scan.points, scan.intensity, scan.ring)
    assert again.read_bytes() == path.read_bytes()


def test_writer_rounds_to_5mm_and_refuses_out_of_range(tmp_path):
    pts = np.array([[1.2341, -5.0, 0.0026], [-99.999, 227.6, 3.0]])
    write_nclt_bin(tmp_path / "a.bin", pts)
    np.testing.assert_allclose(read_nclt_bin(tmp_path / "a.bin").points, pts, atol=0.0025 + 1e-5)
    with pytest.raises(ValueError, match="cannot be packed"):
        write_nclt_bin(tmp_path / "b.bin", [[0, 0, 230.0]])


def test_scans_and_stamps_from_file_names(session):
    assert detect_scan_source(session) == detect_scan_source(session.parent / DATE) == "nclt"
    seq = open_scans(session)
    assert len(seq) == 10 and seq.meta["format"] == "nclt"
    np.testing.assert_array_equal(seq.timestamps, (UTIME0 + 100_000 * np.arange(10)) / 1e6)
    assert [len(seq[i]) for i in (0, 9)] == [40, 49]


def test_velodyne_to_body_is_the_published_one():
    np.testing.assert_allclose(T_BODY_VEL, BODY_VEL, atol=1e-15)
    # the Velodyne's x axis points along the body's -y (yaw -90.7 degrees), 0.957 m above (NED: z down)
    assert T_BODY_VEL[1, 0] < -0.99 and T_BODY_VEL[2, 3] == -0.957


def test_ground_truth_csv_in_the_velodyne_frame(session):
    gt = session.parent / f"groundtruth_{DATE}.csv"
    assert detect_trajectory_format(gt) == "nclt-csv"
    traj = read_trajectory(gt)
    assert traj.meta["dropped_nan_lines"] == [1, 2]
    rows = np.loadtxt(gt, delimiter=",")[2:]
    np.testing.assert_array_equal(traj.timestamps, rows[:, 0] / 1e6)
    want = np.array([pose(*r[1:]) @ BODY_VEL for r in rows])
    np.testing.assert_allclose(traj.poses, want, atol=1e-12)


def test_session_ground_truth_is_sampled_at_the_scans(session):
    assert detect_trajectory_format(session) == "nclt"
    traj = read_trajectory(session)
    stamps = (UTIME0 + 100_000 * np.arange(10)) / 1e6
    np.testing.assert_array_equal(traj.timestamps, stamps)
    want = np.array([pose(*body(0.1 * i)) @ BODY_VEL for i in range(10)])
    np.testing.assert_allclose(traj.poses, want, atol=1e-6)
    assert traj.meta["unposed_scans"] == 0 and traj.meta["file"].endswith(f"groundtruth_{DATE}.csv")


def test_scans_before_the_ground_truth(tmp_path):
    held = read_trajectory(make_session(tmp_path / "a", gt_start=0.05))  # first row 0.05 s late: held
    assert len(held) == 10
    np.testing.assert_allclose(held.poses[0], pose(*body(0.05)) @ BODY_VEL, atol=1e-12)
    late = read_trajectory(make_session(tmp_path / "b", gt_start=0.25))  # 0.25 s late: scans 0 and 1 unposed
    assert len(late) == 8 and late.meta["unposed_scans"] == 2


def test_odometry_is_carried_as_the_warm_start(session):
    seq = open_scans(session)
    odom = read_trajectory(session, "nclt-odometry")
    assert set(seq.trajectories) == {"odometry"}
    np.testing.assert_allclose(seq.trajectories["odometry"].poses, odom.poses, atol=0)
    np.testing.assert_allclose(odom.poses, [pose(*body(0.1 * i)) @ BODY_VEL for i in range(10)], atol=1e-6)
    assert detect_trajectory_format(session / "odometry_mu_100hz.csv") == "nclt-csv"


def test_csv_round_trip(session, tmp_path):
    gt = session.parent / f"groundtruth_{DATE}.csv"
    traj = read_nclt_csv(gt)
    out = tmp_path / "out.csv"
    write_nclt_csv(traj, out)
    back = read_nclt_csv(out)
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)
    np.testing.assert_allclose(np.loadtxt(out, delimiter=","), np.loadtxt(gt, delimiter=",")[2:], atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-500, 500, allow_nan=False)] * 3, *[st.floats(-3.1, 3.1)] * 3),
                min_size=1, max_size=20),
       st.integers(10**15, 2 * 10**15))
def test_csv_parser(tmp_path_factory, rows, utime0):
    path = tmp_path_factory.mktemp("csv") / "odometry_mu.csv"
    path.write_text("".join(f"{utime0 + 10_000 * i}," + ",".join(map(repr, r)) + "\n" for i, r in enumerate(rows)))
    traj = read_nclt_csv(path)
    np.testing.assert_array_equal(traj.timestamps, (utime0 + 10_000 * np.arange(len(rows))) / 1e6)
    np.testing.assert_allclose(traj.poses @ np.linalg.inv(BODY_VEL), [pose(*r) for r in rows], atol=1e-9)


def test_euroc_csv_is_still_euroc(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z\n1403715273262142976,0,0,0,1,0,0,0\n")
    assert detect_trajectory_format(path) == "euroc"


def _break(session: Path, how: str) -> tuple[str, str]:
    """Damage a generated session; returns the command's target and the name the error must carry."""
    gt = session.parent / f"groundtruth_{DATE}.csv"
    lines = gt.read_text().splitlines()
    if how == "columns":
        lines[4] = ",".join(lines[4].split(",")[:6])
        gt.write_text("\n".join(lines) + "\n")
        return str(gt), f"groundtruth_{DATE}.csv:5: 6 columns, expected 7"
    if how == "text":
        lines[5] = lines[5].replace(",0.3,", ",z,")
        gt.write_text("\n".join(lines) + "\n")
        return str(session), f"groundtruth_{DATE}.csv:6: not a number: 'z'"
    if how == "unsorted":
        lines[6], lines[7] = lines[7], lines[6]
        gt.write_text("\n".join(lines) + "\n")
        return str(gt), f"groundtruth_{DATE}.csv:8: unsorted"
    if how == "all-nan":
        gt.write_text("1326030975726043,nan,nan,nan,nan,nan,nan\n")
        return str(gt), "every row has NaN values"
    if how == "missing":
        gt.unlink()
        return str(session), f"groundtruth_{DATE}.csv: missing ground truth"
    if how == "bin-size":
        scan = session / "velodyne_sync" / f"{UTIME0}.bin"
        scan.write_bytes(scan.read_bytes()[:-3])
        return str(session), f"{UTIME0}.bin: size"
    if how == "bin-name":
        (session / "velodyne_sync" / "scan.bin").write_bytes(pack([(1, 2, 3, 4, 5)]))
        return str(session), "scan.bin: expected the scan time in microseconds"
    raise ValueError(how)


@pytest.mark.parametrize("how", ["columns", "text", "unsorted", "all-nan", "missing", "bin-size", "bin-name"])
def test_bad_input_is_one_line_naming_the_file(session, tmp_path, how):
    target, name = _break(session, how)
    with pytest.raises(InputError) as err:
        if how.startswith("bin"):
            open_scans(target)[0]
        else:
            read_trajectory(target)
    assert name in str(err.value) and "\n" not in str(err.value)
    if not how.startswith("bin"):  # (``dm2 info`` shows a session's poses even when a scan is bad)
        assert_one_line_error(run("convert", target, str(tmp_path / "o.txt"), "--to", "tum"), name.split(":")[0])


def test_info_and_convert(session, tmp_path):
    info = run("info", str(session))
    assert info.exit_code == 0, info.output
    for text in ("nclt", "velodyne_sync", "10 scans", f"groundtruth_{DATE}.csv", "poses 'odometry'", "path length"):
        assert text in info.output, info.output
    out = tmp_path / "gt.txt"
    done = run("convert", str(session), str(out), "--to", "tum")
    assert done.exit_code == 0, done.output
    back, ours = read_tum(out), read_trajectory(session)
    np.testing.assert_allclose(back.poses, ours.poses, atol=1e-12)
    np.testing.assert_array_equal(back.timestamps, ours.timestamps)


def test_sampling_is_slerp():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.02, 200))
    poses = np.tile(np.eye(4), (200, 1, 1))
    poses[:, :3, :3] = Rotation.random(200, random_state=4).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(200, 3))
    at = np.sort(rng.uniform(t[0], t[-1], 50))
    got = sample_at(Trajectory(poses, t), at)
    want = Slerp(t, Rotation.from_matrix(poses[:, :3, :3]))(at).as_matrix()
    np.testing.assert_allclose(got.poses[:, :3, :3], want, atol=1e-12)
    np.testing.assert_allclose(got.positions, np.stack([np.interp(at, t, poses[:, c, 3]) for c in range(3)], 1),
                               atol=1e-12)


def test_run_inputs(session):
    """What ``dm2 refine --scans SESSION --gt SESSION`` gets: the odometry as the warm start, the ground
    truth at every scan."""
    inputs = load_inputs(session, None, None, None, ReadOptions(), gt_path=session)
    assert len(inputs.scans) == len(inputs.given) == len(inputs.gt) == 10 and inputs.given_format == "nclt"
    np.testing.assert_allclose(inputs.gt.poses, read_trajectory(session).poses)
