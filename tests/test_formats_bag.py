"""ROS bag adapter: agreement with evo, TF chains against a plain tf2 re-implementation, write/read round
trips, PointCloud2 / LaserScan scans from bags written here, and bad input."""

from __future__ import annotations

import bisect
import functools
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Reader as Reader2
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from dm2_backend.cli.main import cli
from dm2_backend.formats import (
    ReadOptions,
    detect_scan_source,
    detect_trajectory_format,
    open_scans,
    read_trajectory,
    write_trajectory,
)
from dm2_backend.formats.bag import describe
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

BAGS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "bags"


@pytest.fixture(scope="module")
def bags() -> Path:
    if not (BAGS / "ROS_example.bag").exists():
        pytest.skip("shared bags absent")
    return BAGS


def _evo(path: Path, topic: str):
    from evo.tools import file_interface

    reader_t = Reader1 if path.suffix == ".bag" else Reader2
    with reader_t(path) as reader:
        return file_interface.read_bag_trajectory(reader, topic)


def _same_rotations(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> None:
    qa, qb = se3.matrix_to_quat(a, "wxyz"), se3.matrix_to_quat(b, "wxyz")
    np.testing.assert_allclose(qa, qb, atol=tol, rtol=0)


@pytest.mark.parametrize(
    ("name", "topic"),
    [
        ("ROS_example.bag", "groundtruth"),
        ("ROS_example.bag", "ORB-SLAM"),
        ("nav2_turtlebot.mcap", "/odom"),
        ("nav2_turtlebot.mcap", "/amcl_pose"),
    ],
)
def test_agrees_with_evo(bags, name, topic):
    ref = _evo(bags / name, topic)
    traj = read_trajectory(bags / name, None, ReadOptions(topic=topic))
    assert traj.meta["format"] == "bag" and len(traj) == ref.num_poses
    np.testing.assert_array_equal(traj.timestamps, ref.timestamps)
    np.testing.assert_allclose(traj.positions, ref.positions_xyz, atol=1e-9, rtol=0)
    q = np.asarray(ref.orientations_quat_wxyz)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(se3.matrix_to_quat(traj.poses[:, :3, :3], "wxyz"), q, atol=1e-9, rtol=0)
    np.testing.assert_allclose(traj.poses, np.stack(ref.poses_se3), atol=1e-9, rtol=0)
    assert traj.meta["frame_id"] == ref.meta["frame_id"]


# --- TF: a literal, scalar re-implementation of tf2's TimeCache lookups and evo's lookup times ---------


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _tf2_slerp(q0, q1, t):
    dot = sum(a * b for a, b in zip(q0, q1, strict=True))
    s = math.sqrt(sum(a * a for a in q0) * sum(b * b for b in q1))
    theta = math.acos(max(-1.0, min(1.0, abs(dot) / s)))
    if theta == 0:
        return q0
    d, s0, s1 = 1 / math.sin(theta), math.sin((1 - t) * theta), math.sin(t * theta)
    sign = -1.0 if dot < 0 else 1.0
    return [(a * s0 + sign * b * s1) * d for a, b in zip(q0, q1, strict=True)]


@functools.lru_cache(maxsize=4)
def _tf_messages(path: Path):
    """Per child frame: dynamic entries {stamp ns: first entry}, static entries, first dynamic stamp."""
    dynamic, static, start = {}, {}, None
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for topic, is_static in (("/tf", False), ("/tf_static", True)):
            conns = [c for c in reader.connections if c.topic == topic]
            for conn, _, raw in reader.messages(connections=conns) if conns else ():
                for tf in reader.deserialize(raw, conn.msgtype).transforms:
                    ns = tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec
                    tr, ro = tf.transform.translation, tf.transform.rotation
                    entry = (ns, tf.header.frame_id, [tr.x, tr.y, tr.z], [ro.x, ro.y, ro.z, ro.w])
                    if is_static:
                        static[tf.child_frame_id] = entry
                        continue
                    start = ns if start is None else start
                    cache = dynamic.setdefault(tf.child_frame_id, {})
                    cache.setdefault(ns, entry)  # tf2 ignores repeated stamps
    dynamic = {k: [v[s] for s in sorted(v)] for k, v in dynamic.items()}
    return dynamic, {k: [e[0] for e in v] for k, v in dynamic.items()}, static, start


def _reference_tf(path: Path, parent: str, child: str):
    dynamic, dyn_stamps, static, start = _tf_messages(path)

    def link(frame, t):
        if frame in static:
            _, _, p, q = static[frame]
            return p, q
        entries, stamps = dynamic[frame], dyn_stamps[frame]
        if t < stamps[0] or t > stamps[-1]:
            return None
        i = bisect.bisect_right(stamps, t) - 1
        if stamps[i] == t:
            return entries[i][2], entries[i][3]
        (t0, _, p0, q0), (t1, _, p1, q1) = entries[i], entries[i + 1]
        r = (t - t0) / (t1 - t0)
        return [a * (1 - r) + b * r for a, b in zip(p0, p1, strict=True)], _tf2_slerp(q0, q1, r)

    def up(frame):
        path = [frame]
        while path[-1] in dynamic or path[-1] in static:
            path.append((dynamic[path[-1]][0] if path[-1] in dynamic else static[path[-1]])[1])
        return path

    up_c, up_p = up(child), up(parent)
    common = next(f for f in up_c if f in up_p)
    chains = up_c[: up_c.index(common)], up_p[: up_p.index(common)]
    latest = min((dynamic[f][-1][0] for c in chains for f in c if f in dynamic), default=0)
    times = [latest] if latest < start else list(range(start, latest + 1, 10**8))
    poses, stamps = [], []
    for t in times:
        sides = []
        for chain in chains:
            pose = np.eye(4)
            for frame in reversed(chain):
                if (pq := link(frame, t)) is None:
                    break
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = _quat_matrix(pq[1]), pq[0]
                pose = pose @ T
            else:
                sides.append(pose)
        if len(sides) == 2:
            poses.append(np.linalg.inv(sides[1]) @ sides[0])
            stamps.append(t // 10**9 + (t % 10**9) * 1e-9)
    return np.array(poses), np.array(stamps)


@pytest.mark.parametrize(
    ("name", "tf_id"),
    [
        ("tf_example.bag", "/tf:odom.base_link"),
        ("tf_example", "/tf:odom.base_link"),
        ("tf_example/tf_example.db3", "/tf:base_link.odom"),
        ("nav2_turtlebot.mcap", "/tf:map.base_link"),
        ("nav2_turtlebot.mcap", "/tf:odom.oakd_rgb_camera_optical_frame"),
        ("nav2_turtlebot.mcap", "/tf:right_wheel.map"),
    ],
)
def test_tf_chain_matches_tf2_semantics(bags, name, tf_id):
    _, frames = tf_id.split(":")
    parent, child = frames.split(".")
    ref_poses, ref_stamps = _reference_tf(bags / name, parent, child)
    traj = read_trajectory(bags / name, None, ReadOptions(topic=tf_id))
    assert len(traj) == len(ref_stamps) > 100
    np.testing.assert_array_equal(traj.timestamps, ref_stamps)
    np.testing.assert_allclose(np.diff(traj.timestamps), 0.1, atol=1e-6)
    np.testing.assert_allclose(traj.positions, ref_poses[:, :3, 3], atol=1e-9, rtol=0)
    _same_rotations(traj.poses[:, :3, :3], ref_poses[:, :3, :3])
    assert traj.meta["frame_id"] == parent and traj.meta["child_frame_id"] == child


def test_tf_first_pose_is_first_message_and_storages_agree(bags):
    """The first lookup time is the first transform's stamp, where no interpolation happens."""
    opts = ReadOptions(topic="/tf:odom.base_footprint")
    ros1 = read_trajectory(bags / "tf_example.bag", None, opts)
    ros2 = read_trajectory(bags / "tf_example", None, opts)
    np.testing.assert_array_equal(ros1.poses, ros2.poses)
    np.testing.assert_array_equal(ros1.timestamps, ros2.timestamps)
    with AnyReader([bags / "tf_example.bag"]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/tf")
        _, _, raw = next(reader.messages(connections=[conn]))
        tf = reader.deserialize(raw, conn.msgtype).transforms[0]
    assert ros1.timestamps[0] == tf.header.stamp.sec + tf.header.stamp.nanosec * 1e-9
    t, q = tf.transform.translation, tf.transform.rotation
    np.testing.assert_array_equal(ros1.positions[0], [t.x, t.y, t.z])
    _same_rotations(ros1.poses[:1, :3, :3], se3.quat_to_matrix([[q.x, q.y, q.z, q.w]], "xyzw"))


def test_tf_static_only_chain_is_one_pose_at_zero(bags):
    traj = read_trajectory(bags / "nav2_turtlebot.mcap", None, ReadOptions(topic="/tf:base_link.oakd_link"))
    assert len(traj) == 1 and traj.timestamps[0] == 0.0


@pytest.mark.parametrize(
    ("tf_id", "words"),
    [
        ("/tf:odom.nowhere", ["'nowhere'", "base_footprint"]),
        ("/tf:odom.odom", ["same frame"]),
        ("/tfx:odom.base_link", ["no topic '/tfx'", "/tf_static (tf2_msgs/msg/TFMessage)"]),
    ],
)
def test_tf_errors(bags, tf_id, words):
    with pytest.raises(InputError) as err:
        read_trajectory(bags / "tf_example.bag", None, ReadOptions(topic=tf_id))
    assert all(w in err.value.message for w in words), err.value.message


# --- writing -----------------------------------------------------------------------------------------


def _random_trajectory(n: int = 50, t0: float = 1_700_000_000.123456789) -> Trajectory:
    rng = np.random.default_rng(3)
    R = se3.exp_so3(rng.normal(size=(n, 3)))
    poses = se3.make_poses(R, rng.normal(scale=20, size=(n, 3)))
    return Trajectory(poses, t0 + np.cumsum(rng.uniform(0.01, 0.2, n)))


@pytest.mark.parametrize("name", ["out.bag", "out.mcap", "out.db3", "out_folder"])
def test_write_read_round_trip(tmp_path, name):
    traj = _random_trajectory()
    path = tmp_path / name
    write_trajectory(traj, path, "bag")
    write_trajectory(traj, path, "bag")  # overwriting goes through the atomic rename too
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]
    assert detect_trajectory_format(path) == "bag"
    back = read_trajectory(path)
    assert back.meta["topic"] == "/dm2/poses" and back.meta["frame_id"] == "map"
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-12, rtol=0)
    # evo reads what dm2 wrote and agrees to the bit with dm2's reader
    ref = _evo(path, "/dm2/poses")
    np.testing.assert_array_equal(back.timestamps, ref.timestamps)
    np.testing.assert_allclose(back.poses, np.stack(ref.poses_se3), atol=1e-12, rtol=0)


def test_write_topic_and_convert_cli(bags, tmp_path):
    out = tmp_path / "amcl.bag"
    res = CliRunner().invoke(cli, ["convert", str(bags / "nav2_turtlebot.mcap"), str(out), "-t", "/amcl_pose",
                                   "--out-topic", "/gt"])
    assert res.exit_code == 0, res.output
    src = _evo(bags / "nav2_turtlebot.mcap", "/amcl_pose")
    back = read_trajectory(out, None, ReadOptions(topic="/gt"))
    np.testing.assert_array_equal(back.timestamps, src.timestamps)
    np.testing.assert_allclose(back.poses, np.stack(src.poses_se3), atol=1e-12, rtol=0)


def test_write_needs_timestamps(tmp_path):
    traj = Trajectory(se3.identity(3))
    with pytest.raises(InputError, match="needs timestamps"):
        write_trajectory(traj, tmp_path / "x.bag", "bag")
    assert not any(tmp_path.iterdir())


# --- scans -------------------------------------------------------------------------------------------

_CLOUD_DTYPE = np.dtype({
    "names": ["x", "y", "z", "intensity", "ring", "time"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
    "offsets": [0, 4, 8, 16, 20, 24],
    "itemsize": 32,
})


def _cloud_points(k: int) -> np.ndarray:
    pts = np.zeros(6, _CLOUD_DTYPE)  # 2 rows x 3 points
    pts["x"], pts["y"], pts["z"] = np.arange(6) + k, -np.arange(6), 0.5 * k
    pts["intensity"], pts["ring"], pts["time"] = 10.0 * np.arange(6), np.arange(6) % 2, 1e-3 * np.arange(6)
    pts["x"][4] = np.nan
    return pts


def _pointcloud2(ts, k: int):
    t = ts.types
    pts = _cloud_points(k)
    row_step = 3 * 32 + 8  # padded rows
    data = np.zeros((2, row_step), np.uint8)
    data[:, : 3 * 32] = pts.view(np.uint8).reshape(2, 3 * 32)
    field = t["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=_CLOUD_DTYPE.fields[n][1], datatype=d, count=1)
              for n, d in zip(_CLOUD_DTYPE.names, (7, 7, 7, 7, 4, 7), strict=True)]
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, k), height=2, width=3, fields=fields, is_bigendian=False, point_step=32,
        row_step=row_step, data=data.reshape(-1), is_dense=False,
    )


def _laserscan(ts, k: int):
    ranges = np.array([1.0, np.inf, 2.0, np.nan, 0.01, 50.0, 3.0 + k], np.float32)
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=_header(ts, k), angle_min=-np.pi / 2, angle_max=np.pi / 2, angle_increment=np.pi / 6,
        time_increment=0.001, scan_time=0.1, range_min=0.1, range_max=30.0, ranges=ranges,
        intensities=np.arange(7, dtype=np.float32),
    )


def _header(ts, k: int):
    header = ts.types["std_msgs/msg/Header"]
    fields = {"stamp": ts.types["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=250_000_000),
              "frame_id": "lidar"}
    return header(seq=k, **fields) if "seq" in header.__dataclass_fields__ else header(**fields)


def _write_scan_bag(path: Path, ros1: bool, topics=("/points", "/scan")) -> None:
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    writer = Writer1(path) if ros1 else Writer2(path, version=8)
    make = {"/points": (_pointcloud2, "sensor_msgs/msg/PointCloud2"),
            "/scan": (_laserscan, "sensor_msgs/msg/LaserScan")}
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    with writer:
        conns = {t: writer.add_connection(t, make[t][1], typestore=ts) for t in topics}
        for k in range(4):
            for topic in topics:
                msg = make[topic][0](ts, k)
                writer.write(conns[topic], (100 + k) * 10**9 + 300_000_000, serialize(msg, make[topic][1]))


@pytest.mark.parametrize("ros1", [True, False])
def test_pointcloud2_scans(tmp_path, ros1):
    path = tmp_path / ("scans.bag" if ros1 else "scans")
    _write_scan_bag(path, ros1)
    assert detect_scan_source(path) == "bag"
    seq = open_scans(path, None, ReadOptions(topic="/points"))
    assert len(seq) == 4 and not seq.planar
    np.testing.assert_array_equal(seq.timestamps, 100.25 + np.arange(4))
    for k in (3, 0, 2):  # random access
        scan = seq[k]
        pts = _cloud_points(k)
        keep = np.isfinite(pts["x"])
        assert len(scan) == 5 and scan.timestamp == 100 + k + 0.25
        np.testing.assert_array_equal(scan.points, np.stack([pts["x"], pts["y"], pts["z"]], 1)[keep])
        np.testing.assert_array_equal(scan.intensity, pts["intensity"][keep])
        np.testing.assert_array_equal(scan.ring, pts["ring"][keep])
        np.testing.assert_allclose(scan.point_time, pts["time"][keep], rtol=1e-7)


@pytest.mark.parametrize("ros1", [True, False])
def test_laserscan_scans(tmp_path, ros1):
    path = tmp_path / ("scans.bag" if ros1 else "scans")
    _write_scan_bag(path, ros1)
    seq = open_scans(path, None, ReadOptions(topic="/scan"))
    assert len(seq) == 4 and seq.planar
    scan = seq[1]
    angles = -np.pi / 2 + np.pi / 6 * np.array([0, 2, 6])
    r = np.array([1.0, 2.0, 4.0])
    expected = np.stack([r * np.cos(angles), r * np.sin(angles), 0 * r], 1)
    np.testing.assert_allclose(scan.points, expected, atol=1e-6)
    np.testing.assert_array_equal(scan.intensity, [0, 2, 6])
    np.testing.assert_allclose(scan.point_time, [0, 0.002, 0.006])


def test_scan_topic_choice(tmp_path):
    both, one = tmp_path / "both", tmp_path / "one.bag"
    _write_scan_bag(both, ros1=False)
    _write_scan_bag(one, ros1=True, topics=("/scan",))
    with pytest.raises(InputError, match=r"several topics with scans \(/points, /scan\)"):
        open_scans(both)
    assert open_scans(one).meta["topic"] == "/scan"
    with pytest.raises(InputError, match="no topic '/nope'; topics: /points"):
        open_scans(both, None, ReadOptions(topic="/nope"))


def test_scans_from_a_pose_topic(bags):
    with pytest.raises(InputError, match="does not hold scans") as err:
        open_scans(bags / "ROS_example.bag", None, ReadOptions(topic="groundtruth"))
    assert err.value.topic == "groundtruth"


def test_unreadable_cloud_layout(tmp_path):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msg = _pointcloud2(ts, 0)
    msg.fields = [f for f in msg.fields if f.name != "z"]
    with Writer2(tmp_path / "bad", version=8) as writer:
        conn = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        writer.write(conn, 1, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    seq = open_scans(tmp_path / "bad")
    with pytest.raises(InputError, match="no field z") as err:
        seq[0]
    assert err.value.topic == "/points"


# --- bad input and the CLI ---------------------------------------------------------------------------


def test_cli_unknown_topic_lists_topics(bags):
    res = CliRunner().invoke(cli, ["info", str(bags / "ROS_example.bag"), "--topic", "/nope"])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "ROS_example.bag" in lines[0] and "no topic '/nope'" in lines[0]
    assert "groundtruth (geometry_msgs/msg/PoseStamped)" in lines[0]


def test_cli_wrong_message_type(bags):
    res = CliRunner().invoke(cli, ["info", str(bags / "nav2_turtlebot.mcap"), "--topic", "/tf_static"])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
    assert "[topic /tf_static]" in res.output and "tf2_msgs/msg/TFMessage does not hold poses" in res.output


def test_cli_info_describes_topics(bags):
    res = CliRunner().invoke(cli, ["info", str(bags / "tf_example")])
    assert res.exit_code == 0, res.output
    assert "ROS 2 bag folder" in res.output and "518" in res.output
    rows = dict(describe(bags / "nav2_turtlebot.mcap")[:3])
    assert rows == {"storage": "ROS 2 mcap file", "duration": "97.355 s", "messages": "8197"}
    topics = [v.split() for k, v in describe(bags / "nav2_turtlebot.mcap") if k == "topic"]
    assert ["/odom", "nav_msgs/msg/Odometry", "2639"] in topics


def test_several_pose_topics_need_a_choice(bags):
    with pytest.raises(InputError, match="several topics with poses .*groundtruth.*say which with --topic"):
        read_trajectory(bags / "ROS_example.bag")
    with pytest.raises(InputError, match="no topic with poses.*/tf:PARENT.CHILD"):
        read_trajectory(bags / "tf_example.bag")


def test_single_pose_topic_is_chosen(tmp_path):
    write_trajectory(_random_trajectory(), tmp_path / "a.bag", "bag")
    assert read_trajectory(tmp_path / "a.bag").meta["topic"] == "/dm2/poses"


def _write_poses(path: Path, stamps, quats) -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    from dm2_backend.formats.bag_messages import pose_stamped

    with Writer2(path, version=8) as writer:
        conn = writer.add_connection("/p", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for i, ((sec, nsec), q) in enumerate(zip(stamps, quats, strict=True)):
            msg = pose_stamped(ts, sec, nsec, (i, 0, 0), q, "map", i)
            writer.write(conn, i + 1, ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


@pytest.mark.parametrize(
    ("stamps", "quats", "problem"),
    [
        ([(1, 0), (2, 0), (3, 0)], [(0, 0, 0, 1), (0, 0, 0, 0), (0, 0, 0, 1)], "message 1 has quaternion"),
        ([(1, 0), (3, 0), (2, 0)], [(0, 0, 0, 1)] * 3, "unsorted timestamp"),
        ([(1, 0), (1, 0), (2, 0)], [(0, 0, 0, 1)] * 3, "duplicate timestamp"),
    ],
)
def test_bad_pose_messages(tmp_path, stamps, quats, problem):
    _write_poses(tmp_path / "b", stamps, quats)
    with pytest.raises(InputError, match=problem) as err:
        read_trajectory(tmp_path / "b")
    assert err.value.topic == "/p" and str(tmp_path / "b") in err.value.message
    res = CliRunner().invoke(cli, ["info", str(tmp_path / "b"), "--topic", "/p"])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1


@pytest.mark.parametrize("name", ["junk.bag", "junk.mcap", "junk.db3", "truncated.bag"])
def test_unreadable_files(bags, tmp_path, name):
    path = tmp_path / name
    if name.startswith("truncated"):
        data = (bags / "tf_example.bag").read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        path.write_bytes(b"not a bag at all\n" * 10)
    res = CliRunner().invoke(cli, ["info", str(path)])
    assert res.exit_code == 2, res.output
    assert len(res.output.strip().splitlines()) == 1 and name in res.output and "cannot" in res.output


def test_folder_without_metadata_is_not_a_bag(bags, tmp_path):
    shutil.copy(bags / "tf_example" / "tf_example.db3", tmp_path / "x.db3")
    assert detect_trajectory_format(tmp_path / "x.db3") == "bag"
    assert len(read_trajectory(tmp_path / "x.db3", None, ReadOptions(topic="/tf:odom.base_link"))) == 517
    try:
        assert detect_trajectory_format(tmp_path) != "bag"
    except InputError:
        pass
    assert detect_trajectory_format(bags / "tf_example") == "bag"


def _write_tf_bag(path: Path, transforms: list[tuple[int, str, str, tuple, tuple]], static=()) -> None:
    """/tf (one transform per message) and /tf_static from (stamp ns, parent, child, xyz, xyzw) rows."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types

    def stamped(ns, parent, child, xyz, q):
        header = t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=parent)
        transform = t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        msgtype = t["geometry_msgs/msg/TransformStamped"]
        return msgtype(header=header, child_frame_id=child, transform=transform)

    with Writer2(path, version=8) as writer:
        for topic, rows in (("/tf", transforms), ("/tf_static", static)):
            conn = writer.add_connection(topic, "tf2_msgs/msg/TFMessage", typestore=ts)
            for i, row in enumerate(rows):
                msg = t["tf2_msgs/msg/TFMessage"](transforms=[stamped(*row)])
                writer.write(conn, i + 1, ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))


def test_tf_interpolation_and_repeated_stamps(tmp_path):
    s = math.sqrt(0.5)
    _write_tf_bag(tmp_path / "b", [
        (10**9, "odom", "base", (0, 0, 0), (0, 0, 0, 1)),
        (10**9, "odom", "base", (100, 0, 0), (0, 0, 0, 1)),  # repeated stamp: tf2 keeps the first
        (2 * 10**9, "odom", "base", (1, 0, 0), (0, 0, s, s)),  # 90 degrees about z
    ], static=[(0, "base", "laser", (0, 2, 0), (0, 0, 0, 1))])
    traj = read_trajectory(tmp_path / "b", None, ReadOptions(topic="/tf:odom.laser"))
    np.testing.assert_allclose(traj.timestamps, 1.0 + 0.1 * np.arange(11), atol=1e-12)
    yaw = np.pi / 2 * np.arange(11) / 10
    x = 0.1 * np.arange(11) - 2 * np.sin(yaw)
    y = 2 * np.cos(yaw)
    np.testing.assert_allclose(traj.positions, np.stack([x, y, 0 * x], 1), atol=1e-12)
    np.testing.assert_allclose(se3.to_xy_yaw(traj.poses)[:, 2], yaw, atol=1e-12)


@pytest.mark.parametrize(
    ("rows", "problem"),
    [
        ([(1, "a", "b", (0, 0, 0), (0, 0, 0, 1)), (2, "c", "b", (0, 0, 0), (0, 0, 0, 1))], "several parents"),
        ([(1, "a", "b", (0, 0, 0), (0, 0, 0, 1)), (2, "b", "a", (0, 0, 0), (0, 0, 0, 1))], "form a loop"),
        ([(1, "a", "b", (0, 0, 0), (0, 0, 0, 2))], "has quaternion"),
        ([(1, "a", "b", (0, 0, 0), (0, 0, 0, 1)), (1, "c", "d", (0, 0, 0), (0, 0, 0, 1))], "not connected"),
    ],
)
def test_tf_bad_trees(tmp_path, rows, problem):
    _write_tf_bag(tmp_path / "b", rows)
    with pytest.raises(InputError, match=problem) as err:
        read_trajectory(tmp_path / "b", None, ReadOptions(topic="/tf:a.b" if problem != "not connected"
                                                          else "/tf:a.d"))
    assert err.value.topic is not None


@pytest.mark.parametrize("name", ["tf_example.bag", "tf_example", "nav2_turtlebot.mcap"])
def test_info_lists_tf_frame_pairs_with_their_topic_ids(bags, name):
    """`dm2 info BAG` lists every TF pair (parent -> child, count, topic) with the --topic id that reads it."""
    expected: dict[tuple[str, str, str], int] = {}
    with AnyReader([bags / name], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic.startswith("/tf")]):
            for tf in reader.deserialize(raw, conn.msgtype).transforms:
                key = (tf.header.frame_id, tf.child_frame_id, conn.topic)
                expected[key] = expected.get(key, 0) + 1
    result = CliRunner().invoke(cli, ["info", str(bags / name)], obj={})
    assert result.exit_code == 0, result.output
    listed = {}
    for line in result.output.splitlines():
        if line.startswith("tf "):
            pair, rest = line[2:].strip().split("  ", 1)
            parent, child = pair.split(" -> ")
            count, _, topic = rest.split("--topic")[0].strip().partition(" on ")
            tf_id = rest.split("--topic ")[1]
            assert tf_id == f"/tf:{parent}.{child}"
            listed[(parent, child, topic)] = int(count)
    assert listed == expected
    parent, child, _ = max(expected, key=expected.get)  # the busiest dynamic pair reads as typed
    traj = read_trajectory(bags / name, None, ReadOptions(topic=f"/tf:{parent}.{child}"))
    assert len(traj) > 10
