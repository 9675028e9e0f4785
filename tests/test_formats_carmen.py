"""CARMEN logs: the Freiburg benchmark files, both dialects, the line parser, writing, bad input, CLI."""

from __future__ import annotations

import bz2
import functools
import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from dm2_backend.cli.main import cli
from dm2_backend.formats import ReadOptions, carmen, detect_trajectory_format, open_scans, read_trajectory
from dm2_backend.formats.relations import read_relations
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.planar_returns import isolated_long_returns
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen"


def data(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} absent")
    return path


@functools.lru_cache(maxsize=4)
def _raw(path: Path) -> tuple[str, ...]:
    opener = bz2.open if path.name.endswith(".bz2") else gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rt", encoding="latin-1") as fh:
        return tuple(fh.read().split("\n"))


def raw_lines(path: Path) -> list[str]:
    opener = bz2.open if path.name.endswith(".bz2") else gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rt", encoding="latin-1") as fh:
        return fh.read().split("\n")


def flaser_tails(path: Path) -> list[list[str]]:
    """The last 9 words of every FLASER line: laser pose, odometry pose, ipc_timestamp, host, logger time."""
    return [line.rsplit(None, 9)[1:] for line in _raw(path) if line.startswith("FLASER ")]


def run_cli(*args: str):
    return CliRunner().invoke(cli, list(args), obj={})


def one_line_error(result, *parts: str) -> None:
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1, err
    for part in parts:
        assert part in err, err


# ---------------------------------------------------------------- the real logs


@pytest.mark.parametrize(
    "name, scans, odom", [("aces.clf.bz2", 7374, 7375), ("intel.clf.bz2", 13631, 26915)]
)
def test_benchmark_logs_counts_stamps_and_poses_match_the_text(name, scans, odom):
    path = data(name)
    seq = open_scans(path)
    traj = read_trajectory(path)
    assert len(seq) == len(traj) == scans
    assert len(read_trajectory(path, options=ReadOptions(topic="ODOM"))) == odom
    tails = flaser_tails(path)
    stamps = np.array([float(w[6]) for w in tails])
    assert np.array_equal(seq.timestamps, stamps) and np.array_equal(traj.timestamps, stamps)
    assert traj.timestamps.dtype == np.float64 and traj.planar and seq.planar
    laser = np.array([[float(v) for v in w[0:3]] for w in tails])
    odo = np.array([[float(v) for v in w[3:6]] for w in tails])
    xyt = se3.to_xy_yaw(traj.poses)
    assert np.abs(xyt[:, :2] - laser[:, :2]).max() < 1e-12
    assert np.abs(se3.wrap_angle(xyt[:, 2] - laser[:, 2])).max() < 1e-12
    odometry = se3.to_xy_yaw(seq.trajectories["odometry"].poses)
    assert np.abs(odometry[:, :2] - odo[:, :2]).max() < 1e-12
    # Freiburg logs: laser at the robot centre, so both poses agree
    assert np.abs(seq.trajectories["logged"].poses - seq.trajectories["odometry"].poses).max() < 1e-12


def test_scans_follow_carmen_beam_angles_and_drop_max_range():
    path = data("aces.clf.bz2")
    seq = open_scans(path)
    assert seq.meta["max_range"] == 50.0  # ACES saturates at 50.00
    words = [line.split() for line in _raw(path) if line.startswith("FLASER ")]
    for i in (0, 1000, 7373):
        r = np.array([float(v) for v in words[i][2:182]])
        keep = (r > 0) & (r < 50.0)
        keep &= ~isolated_long_returns(r, keep, math.pi / 180)  # one beam far beyond a surface: glass, open doors
        a = -math.pi / 2 + np.arange(180) * math.pi / 180  # CARMEN: -90 .. +89 deg
        expect = np.c_[r * np.cos(a), r * np.sin(a), np.zeros(180)][keep]
        scan = seq[i]
        assert scan.points.dtype == np.float32 and scan.timestamp == float(words[i][-3])
        assert np.abs(scan.points - expect).max() < 1e-4
        assert np.all(np.linalg.norm(scan.points, axis=1) < 50.0) and np.all(scan.points[:, 2] == 0)


def test_intel_points_are_plausible_and_unsorted_stamps_are_kept_in_log_order():
    seq = open_scans(data("intel.clf.bz2"))
    assert seq.meta["unsorted_timestamps"] == 631
    for i in np.linspace(0, len(seq) - 1, 25).astype(int):
        pts = seq[int(i)].points
        assert 20 <= len(pts) <= 180
        assert np.linalg.norm(pts, axis=1).max() < 80.0 and np.linalg.norm(pts, axis=1).min() > 0.05


@pytest.mark.parametrize("name, count", [("aces-corrected.log.gz", 440), ("intel-corrected.log.gz", 910)])
def test_corrected_dialect_parses(name, count):
    path = data(name)
    seq = open_scans(path)
    traj = read_trajectory(path)
    assert len(seq) == len(traj) == count
    tails = flaser_tails(path)
    assert np.array_equal(traj.timestamps, [float(w[6]) for w in tails])
    assert np.allclose(se3.to_xy_yaw(traj.poses)[:, :2], [[float(v) for v in w[0:2]] for w in tails])
    assert 100 < len(seq[count // 2]) <= 180


@pytest.mark.parametrize("name, count", [("aces.relations", 1279), ("intel.relations", 2984)])
def test_relations_reference_flaser_stamps(name, count):
    rel = read_relations(data(name))
    assert rel.shape == (count, 8) and rel.dtype == np.float64
    stamps = set(read_trajectory(data(name.replace(".relations", ".clf.bz2"))).timestamps.tolist())
    assert all(t in stamps for t in rel[:, :2].ravel())


# ---------------------------------------------------------------- writing


def test_rewrite_with_template_keeps_every_other_byte(tmp_path):
    src = data("aces.clf.bz2")
    traj = read_trajectory(src)
    rng = np.random.default_rng(1)
    xyt = se3.to_xy_yaw(traj.poses) + rng.normal(0, 0.2, (len(traj), 3))
    out = tmp_path / "refined.clf"
    carmen.write_carmen(out, traj.with_poses(se3.from_xy_yaw(xyt)), src)
    before, after = raw_lines(src), raw_lines(out)
    assert len(before) == len(after)
    for a, b in zip(before, after, strict=True):
        if not a.startswith("FLASER "):
            assert a == b
        else:
            wa, wb = a.rsplit(None, 9), b.rsplit(None, 9)
            assert wa[0] == wb[0] and wa[4:] == wb[4:]  # ranges, odometry, stamps, host
    back = read_trajectory(out)
    assert np.array_equal(back.timestamps, traj.timestamps)
    got = se3.to_xy_yaw(back.poses)
    assert np.abs(got[:, :2] - xyt[:, :2]).max() <= 5e-7 + 1e-12
    assert np.abs(se3.wrap_angle(got[:, 2] - xyt[:, 2])).max() <= 5e-7 + 1e-12
    odom = read_trajectory(out, options=ReadOptions(pose_source="odometry"))
    assert np.array_equal(odom.poses, traj.poses)  # odometry fields untouched


@pytest.mark.parametrize("suffix", [".log", ".log.gz", ".clf.bz2"])
def test_identity_rewrite_is_byte_identical_and_compressed_by_suffix(tmp_path, suffix):
    src = data("aces-corrected.log.gz")
    out = tmp_path / f"same{suffix}"
    result = run_cli("convert", str(src), str(out))
    assert result.exit_code == 0, result.output
    assert raw_lines(out) == raw_lines(src)


def test_subset_drops_unmatched_messages_and_overwrite_odometry(tmp_path):
    src = data("aces-corrected.log.gz")
    traj = read_trajectory(src)
    sub = traj.subset(slice(0, None, 4)).transformed(left=se3.from_xy_yaw(np.array([1.0, -2.0, 0.3])))
    out = tmp_path / "sub.log"
    carmen.write_carmen(out, sub, src, overwrite_odometry=True)
    back = read_trajectory(out)
    odom = read_trajectory(out, options=ReadOptions(pose_source="odometry"))
    assert len(back) == len(sub) and np.array_equal(back.timestamps, sub.timestamps)
    assert np.abs(back.poses - sub.poses).max() < 2e-6 and np.abs(odom.poses - sub.poses).max() < 2e-6
    assert sum(not line.startswith("FLASER") for line in raw_lines(out)) == sum(
        not line.startswith("FLASER") for line in raw_lines(src)
    )


def test_write_without_template_round_trips_as_odom(tmp_path):
    stamps = np.array([976052857.33753, 976052857.348896, 1.5e9 + 1 / 3])
    xyt = np.array([[0, 0, 0], [1.25, -3, 3.1], [2, 2, -1]])
    traj = Trajectory(se3.from_xy_yaw(xyt), stamps, planar=True)
    out = tmp_path / "poses.log.bz2"
    carmen.write_carmen(out, traj)
    assert detect_trajectory_format(out) == "carmen"
    back = read_trajectory(out)
    assert np.array_equal(back.timestamps, stamps) and np.abs(back.poses - traj.poses).max() < 1e-6


def test_writer_refuses_bad_trajectories(tmp_path):
    src = data("aces-corrected.log.gz")
    traj = read_trajectory(src)
    lifted = traj.poses.copy()
    lifted[3, 2, 3] = 0.5
    with pytest.raises(InputError, match="not planar"):
        carmen.write_carmen(tmp_path / "a.log", traj.with_poses(lifted), src)
    shifted = Trajectory(traj.poses, traj.timestamps + 0.01, planar=True)
    with pytest.raises(InputError, match="no template message"):
        carmen.write_carmen(tmp_path / "b.log", shifted.subset(slice(0, 5)), src)
    assert not (tmp_path / "b.log").exists()


# ---------------------------------------------------------------- line parser (hypothesis)

finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
ranges = st.lists(st.floats(0, 90, allow_nan=False).map(lambda v: round(v, 2)), min_size=0, max_size=40)
stamp = st.floats(0, 2e9, allow_nan=False)


def _text(v: float) -> str:
    return repr(float(v))


@settings(max_examples=60, deadline=None)
@given(ranges, st.lists(finite, min_size=6, max_size=6), stamp, st.booleans())
def test_flaser_line_round_trip(rs, pose, ts, with_logger):
    logger = " 0.25" if with_logger else ""
    body = " ".join(map(_text, rs + pose))
    line = f"FLASER {len(rs)} {body} {_text(ts)} myhost{logger}"
    msg = carmen.parse_line(line, 7, "x.clf")
    assert msg.kind == "FLASER" and msg.timestamp == ts and msg.host == "myhost"
    assert msg.laser_pose == tuple(pose[:3]) and msg.robot_pose == tuple(pose[3:])
    assert np.array_equal(msg.ranges, np.array(rs, dtype=np.float32))
    assert msg.logger_timestamp == (0.25 if with_logger else None)
    words = line.split()
    del words[2 + len(rs) // 2]  # one word missing: num_readings no longer matches
    with pytest.raises(InputError, match=r"x\.clf:7: FLASER"):
        carmen.parse_line(" ".join(words), 7, "x.clf")


@settings(max_examples=60, deadline=None)
@given(ranges, ranges, st.lists(finite, min_size=11, max_size=11), stamp,
       st.sampled_from(["ROBOTLASER1", "RAWLASER1", "RAWLASER"]))
def test_config_laser_line_round_trip(rs, rem, values, ts, kind):
    start, step, maxr = -1.5, 0.01, 81.9
    head = f"{kind} 0 {start} 3.14 {step} {maxr} 0.01 0 {len(rs)} {' '.join(map(_text, rs))} {len(rem)} "
    head += " ".join(map(_text, rem))
    tail = " ".join(map(_text, values)) + " " if kind == "ROBOTLASER1" else ""
    msg = carmen.parse_line(f"{head} {tail}{_text(ts)} h 1.0", 3, "r.log")
    assert msg.kind == kind and msg.timestamp == ts and msg.max_range == maxr
    assert (msg.start_angle, msg.angular_resolution) == (start, step)
    assert np.array_equal(msg.ranges, np.float32(rs)) and np.array_equal(msg.remissions, np.float32(rem))
    if kind == "ROBOTLASER1":
        assert msg.laser_pose == tuple(values[:3]) and msg.robot_pose == tuple(values[3:6])
    else:
        assert msg.laser_pose is None
    with pytest.raises(InputError, match=r"r\.log:3:"):
        carmen.parse_line(f"{head} {tail}{_text(ts)} h 1.0 extra", 3, "r.log")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(ranges, st.lists(finite, min_size=6, max_size=6), stamp), min_size=1, max_size=8))
def test_bulk_parser_agrees_with_the_line_parser(tmp_path_factory, records):
    lines = ["# comment", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for rs, pose, ts in records:
        pose_text = " ".join(map(_text, pose))
        lines.append(f"FLASER {len(rs)} {' '.join(map(_text, rs))} {pose_text} {_text(ts)} h 0.5")
        lines.append(f"ODOM {' '.join(map(_text, pose))} {_text(ts)} h 0.5")
    path = tmp_path_factory.mktemp("bulk") / "b.log"
    path.write_text("\n".join(lines) + "\n")
    log = carmen.parse_log(path)
    for kind in ("FLASER", "ODOM"):
        assert len(log.messages[kind]) == len(records)
        for msg in log.messages[kind]:
            ref = carmen.parse_line(lines[msg.line - 1], msg.line, path)
            for name in ("timestamp", "host", "logger_timestamp", "laser_pose", "robot_pose", "pose_token"):
                assert getattr(msg, name) == getattr(ref, name)
            assert (msg.ranges is None and ref.ranges is None) or np.array_equal(msg.ranges, ref.ranges)


# ---------------------------------------------------------------- compression, other messages, options

CFG = "0 -1.5707963267948966 3.14159 1.5707963267948966 10.0 0.01 0"
LOG = f"""# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp
PARAM robot_frontlaser_offset 0.2 nohost 0
SYNC start 1.0 h 0.0
ODOM 0.0 0.0 0.0 0 0 0 1.0 h 0.0
ROBOTLASER1 {CFG} 3 1.0 10.0 2.0 0 0.2 0.0 0.0 0.0 0.0 0.0 0 0 0 0 0 1.0 h 0.0
RAWLASER1 {CFG} 3 1.0 10.0 2.0 3 5 6 7 1.5 h 0.5
ODOM 1.0 0.0 1.0 0 0 0 2.0 h 1.0
ROBOTLASER1 {CFG} 3 1.0 10.0 2.0 0 1.1080604611736280 0.1682941969615793 1.0 1.0 0.0 1.0 0 0 0 0 0 2.0 h 1.0
TRUEPOS 0 0 0 0 0 0 2.0 h 1.0
"""


@pytest.mark.parametrize("compress", ["", ".gz", ".bz2"])
def test_robotlaser_offset_rawlaser_interpolation_and_compression(tmp_path, compress):
    plain = LOG.encode()
    data_bytes = {"": plain, ".gz": gzip.compress(plain), ".bz2": bz2.compress(plain)}[compress]
    path = tmp_path / f"small.log{compress}"
    path.write_bytes(data_bytes)
    seq = open_scans(path)
    assert seq.meta["carmen_message"] == "ROBOTLASER1" and len(seq) == 2
    # beams at -90, 0, +90 deg; 10.0 is max range -> dropped; offset 0.2 m forward
    assert np.allclose(seq[0].points, [[0.2, -1.0, 0.0], [0.2, 2.0, 0.0]], atol=1e-6)
    logged = se3.to_xy_yaw(seq.trajectories["logged"].poses)
    assert np.allclose(logged, [[0, 0, 0], [1.0, 0.0, 1.0]], atol=1e-12)  # laser (+) offset^-1
    assert np.allclose(seq.trajectories["odometry"].poses, seq.trajectories["logged"].poses, atol=1e-12)
    raw = open_scans(path, options=ReadOptions(topic="RAWLASER1"))
    assert len(raw) == 1 and np.allclose(raw[0].intensity, [5, 7])
    assert np.allclose(se3.to_xy_yaw(raw.trajectories["odometry"].poses), [[0.5, 0, 0.5]])
    assert len(read_trajectory(path, options=ReadOptions(topic="ODOM"))) == 2
    with pytest.raises(InputError, match="no FLASER messages"):
        open_scans(path, options=ReadOptions(topic="FLASER"))
    wide = open_scans(path, options=ReadOptions(max_range=100.0, laser_offset=(0, 0, 0)))
    assert len(wide[0]) == 3


def test_sniff_generic_log_suffix(tmp_path):
    good = tmp_path / "robot.log"
    good.write_text(LOG)
    assert carmen.sniff(good) and detect_trajectory_format(good) == "carmen"
    other = tmp_path / "other.log"
    other.write_text("2024-01-01 12:00 INFO started\n")
    assert not carmen.sniff(other)


# ---------------------------------------------------------------- bad input

FLASER_OK = "FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 5.0 h 0.0"
BAD = {
    "truncated line": ("FLASER 3 1.0 2.0", "needs 14 words"),
    "wrong num_readings": ("FLASER 4 1.0 2.0 3.0 0 0 0 0 0 0 5.0 h 0.0", "num_readings=4"),
    "nan range": ("FLASER 3 1.0 nan 3.0 0 0 0 0 0 0 5.0 h 0.0", "NaN"),
    "nan stamp": ("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 nan h 0.0", "ipc_timestamp"),
    "inf pose": ("ODOM 0 inf 0 0 0 0 6.0 h 0.0", "NaN or infinite"),
    "not a number": ("ODOM 0 x 0 0 0 0 6.0 h 0.0", "'x' is not a number"),
    "non-integer count": ("FLASER 3.5 1.0 2.0 3.0 0 0 0 0 0 0 5.0 h 0.0", "not an integer"),
    "wrapped line": ("1.0 2.0 3.0", "not a CARMEN message"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_lines_name_file_and_line(tmp_path, case):
    line, problem = BAD[case]
    path = tmp_path / "bad.clf"
    path.write_text(f"# header\n{FLASER_OK}\n{line}\n")
    with pytest.raises(InputError) as info:
        read_trajectory(path)
    assert info.value.line == 3 and problem in info.value.problem and str(path) in info.value.message
    one_line_error(run_cli("info", str(path)), f"{path}:3:", problem)


def test_bad_files(tmp_path):
    empty = tmp_path / "empty.clf"
    empty.write_text("# only a comment\nPARAM a b nohost 0\n")
    with pytest.raises(InputError, match="no laser or ODOM"):
        read_trajectory(empty)
    cut = tmp_path / "cut.clf.gz"
    cut.write_bytes(gzip.compress(((FLASER_OK + "\n") * 200).encode())[:-30])
    with pytest.raises(InputError, match="cannot decompress"):
        read_trajectory(cut)
    one_line_error(run_cli("info", str(cut)), str(cut))
    rel = tmp_path / "bad.relations"
    rel.write_text("1 2 0 0 0 0 0 0\n1 2 0 0 0 0 nan 0\n")
    with pytest.raises(InputError, match=r"bad\.relations:2: pitch"):
        read_relations(rel)
    rel.write_text("1 2 0 0 0 0 0\n")
    with pytest.raises(InputError, match="8 values"):
        read_relations(rel)


def test_cli_info_on_aces():
    result = run_cli("info", str(data("aces.clf.bz2")))
    assert result.exit_code == 0, result.output
    assert "carmen" in result.output and "7374" in result.output and "FLASER 7374" in result.output
