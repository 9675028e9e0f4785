"""Fuzzing of dm2's readers: seed inputs per format family, mutations, and the oracle.

Shared by the in-suite budget (``tests/test_fuzz.py``) and the benchmark (``benchmarks/fuzz.py``).

* A *family* is one input kind (TUM, KITTI, ..., ROS 1 bags, configs). Its seeds are small valid inputs
  written here with dm2's own writers or by hand (an input is a mapping ``relative path -> bytes``; the entry
  is the path handed to dm2, a file or a folder).
* :func:`mutate` derives a bad input from a seed: truncation, byte flips, inserted / deleted / duplicated
  bytes or lines, NaN / inf / huge numbers, wrong column counts, non-UTF-8 bytes, empty files, duplicated or
  unsorted stamps, overlong tokens; structure-aware variants mutate inside gzip / bzip2 streams, ``.npz``
  members and PNG chunks (with the CRC fixed, so the decoder sees the change).
* :func:`check` is the oracle: it runs what ``dm2 info`` runs (:func:`dm2_backend.cli.info.describe`) and,
  for trajectories, what ``dm2 convert`` runs (read, write TUM, read the TUM back). Every input must end as
  a *clean read* (finite values, an output dm2 reads back) or a *clean error* (an :class:`InputError`, or
  the OS errors the CLI turns into one line, whose message is one line naming the input); anything else is a
  failure of a kind: ``exception:<Type>``, ``multi-line``, ``unnamed``, ``non-finite``, ``read-back``,
  ``leftover``, ``slow``, ``memory`` (and, in the benchmark's subprocess, ``signal:<name>`` and ``timeout``).
"""

from __future__ import annotations

import bz2
import gzip
import io
import json
import math
import re
import shutil
import struct
import tempfile
import time
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.runtime.errors import InputError

#: an input: relative path -> bytes ("." is never used; the entry names the path handed to dm2)
Files = dict[str, bytes]

SLOW_S = 10.0


@dataclass
class Seed:
    files: Files
    #: path (relative) handed to dm2: a file of ``files`` or a folder holding them
    entry: str
    #: the relative paths a mutation may change
    targets: tuple[str, ...]
    #: bag topics to read besides the default (None = no --topic)
    topics: tuple[str | None, ...] = (None,)


@dataclass
class Family:
    name: str
    build: Callable[[Path], list[Seed]]
    #: "text", "binary", "gz", "bz2", "npz", "png": how mutations see the target bytes
    kinds: dict[str, str] = field(default_factory=dict)
    #: run the ``dm2 convert`` path too (read, write TUM, read back)
    convert: bool = True
    #: instead of info/convert: a custom reader (configs)
    custom: Callable[[Path], None] | None = None


# ---------------------------------------------------------------------------------------------- seeds


def _walk(n: int, rng: np.random.Generator, planar: bool = False):
    from dm2_backend.kernel.geometry import se3
    from dm2_backend.kernel.trajectory import Trajectory

    yaw = np.cumsum(rng.normal(0, 0.1, n))
    xy = np.cumsum(np.stack([np.cos(yaw), np.sin(yaw)], 1) * 0.5, axis=0)
    if planar:
        poses = se3.from_xy_yaw(np.column_stack([xy, yaw]))
    else:
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        poses = se3.from_xyz_quat(np.column_stack([xy, rng.normal(0, 0.1, n)]), q, "xyzw")
    return Trajectory(poses, 1000.0 + 0.1 * np.arange(n), planar=planar)


def _written(tmp: Path, names: list[str]) -> Files:
    return {n: (tmp / n).read_bytes() for n in names}


def _seeds_tum(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.tum import write_tum

    write_tum(_walk(12, np.random.default_rng(1)), tmp / "traj.txt")
    hand = b"# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n1.5,1,0,0,0,0,0.7071067811865476,0.7071067811865476\n"
    return [Seed(_written(tmp, ["traj.txt"]), "traj.txt", ("traj.txt",)),
            Seed({"hand.tum": hand}, "hand.tum", ("hand.tum",))]


def _seeds_kitti(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.kitti import write_kitti
    from dm2_backend.formats.registry import ReadOptions

    (tmp / "seq").mkdir()
    write_kitti(_walk(10, np.random.default_rng(2)), tmp / "seq" / "poses.txt", ReadOptions(times=tmp / "seq" /
                                                                                             "times.txt"))
    files = _written(tmp, ["seq/poses.txt", "seq/times.txt"])
    return [Seed(files, "seq/poses.txt", ("seq/poses.txt", "seq/times.txt")),
            Seed({"00.kitti": files["seq/poses.txt"]}, "00.kitti", ("00.kitti",))]


def _seeds_euroc(tmp: Path) -> list[Seed]:
    from dm2_backend.kernel.geometry import se3

    traj = _walk(10, np.random.default_rng(3))
    xyz, q = se3.to_xyz_quat(traj.poses, "wxyz")
    head = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    long = [head + ", v_x, v_y, v_z, b_w_x, b_w_y, b_w_z, b_a_x, b_a_y, b_a_z"]
    short = [head]
    for i in range(len(traj)):
        row = [str(1403636579758555392 + i * 5_000_000)] + [repr(float(v)) for v in (*xyz[i], *q[i])]
        short.append(",".join(row))
        long.append(",".join(row + ["0.1"] * 9))
    return [Seed({"data.csv": ("\n".join(long) + "\n").encode()}, "data.csv", ("data.csv",)),
            Seed({"gt.csv": ("\n".join(short) + "\n").encode()}, "gt.csv", ("gt.csv",))]


def _seeds_g2o(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.g2o import write_g2o
    from dm2_backend.kernel.geometry import se3
    from dm2_backend.kernel.pose_graph import PoseGraph

    seeds = []
    for planar, name in ((False, "graph3d.g2o"), (True, "graph2d.g2o")):
        traj = _walk(8, np.random.default_rng(4), planar=planar)
        graph = PoseGraph.from_trajectory(traj)
        loop = np.array([[0, 7]])
        graph.edges = np.concatenate([graph.edges, loop])
        graph.relative = np.concatenate([graph.relative, se3.relative(traj.poses[:1], traj.poses[7:8])])
        graph.information = np.concatenate([graph.information, graph.information[:1] * 2])
        graph.fixed = [0]
        write_g2o(graph, tmp / name)
        seeds.append(Seed(_written(tmp, [name]), name, (name,)))
    edges_only = b"EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0.1 1 0 0 1 0 1\nVERTEX_XY 5 1 2\n"
    seeds.append(Seed({"edges.g2o": edges_only}, "edges.g2o", ("edges.g2o",)))
    return seeds


_CARMEN_HAND = """# CARMEN Logfile
# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp
PARAM robot_frontlaser_offset 0.1 host 0
PARAM robot_frontlaser_side_offset 0.0 host 0
ODOM 0.0 0.0 0.0 0 0 0 1.00 host 0.01
FLASER 5 1.0 1.5 2.0 2.5 3.0 0.1 0.0 0.0 0.0 0.0 0.0 1.05 host 0.02
ODOM 0.1 0.0 0.01 0 0 0 1.10 host 0.10
FLASER 5 1.1 1.6 2.1 2.6 3.1 0.2 0.0 0.01 0.1 0.0 0.01 1.15 host 0.12
ROBOTLASER1 0 -1.5708 3.1416 0.7854 20.0 0.1 0 5 1.0 2.0 3.0 4.0 5.0 0 0.1 0.0 0.0 0.0 0.0 0.0 0 0 0.5 0.5 0 \
1.20 host 0.2
RAWLASER1 0 -1.5708 3.1416 0.7854 20.0 0.1 0 5 1.0 2.0 3.0 4.0 5.0 0 1.25 host 0.25
ODOM 0.2 0.0 0.02 0 0 0 1.30 host 0.30
FLASER 5 1.2 1.7 2.2 2.7 3.2 0.3 0.0 0.02 0.2 0.0 0.02 1.35 host 0.32
SYNC 1 2 3 host 1.4
"""


def _carmen_files(tmp: Path, name: str, compress: Callable[[bytes], bytes]) -> list[Seed]:
    from dm2_backend.formats.carmen import write_carmen

    write_carmen(tmp / ("odom" + name), _walk(8, np.random.default_rng(5), planar=True))
    return [Seed({"hand" + name: compress(_CARMEN_HAND.encode())}, "hand" + name, ("hand" + name,)),
            Seed(_written(tmp, ["odom" + name]), "odom" + name, ("odom" + name,))]


def _seeds_carmen(tmp: Path) -> list[Seed]:
    return _carmen_files(tmp, ".log", lambda b: b)


def _seeds_carmen_compressed(tmp: Path) -> list[Seed]:
    return (_carmen_files(tmp, ".log.gz", lambda b: gzip.compress(b, mtime=0))
            + _carmen_files(tmp, ".clf.bz2", bz2.compress))


def _seeds_priors(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.dm2_priors import write_priors
    from dm2_backend.kernel.geometry import se3

    traj = _walk(6, np.random.default_rng(6))
    groups = np.array([[1, 2], [0, 2], [1, 3], [2, 4], [3, 5], [4, -1]])
    rel = np.stack([se3.relative(traj.poses[i:i + 1].repeat(2, 0), traj.poses[np.maximum(g, 0)])
                    for i, g in enumerate(groups)])
    write_priors(tmp / "prior", traj.poses, groups, rel)
    names = ["prior/init_pose.npy", "prior/group_matrix.npy", "prior/pairwise_pose.npy"]
    return [Seed(_written(tmp, names), "prior/init_pose.npy", tuple(names))]


def _cloud(n: int = 16, seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(0, 5, (n, 3)).astype(np.float32)


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def _seeds_npy(tmp: Path) -> list[Seed]:
    pts = _cloud()
    structured = np.zeros(len(pts), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                                     ("ring", "<u2")])
    for i, k in enumerate("xyz"):
        structured[k] = pts[:, i]
    return [Seed({"000001.npy": _npy_bytes(np.column_stack([pts, np.ones(len(pts), np.float32)]))},
                 "000001.npy", ("000001.npy",)),
            Seed({"cloud.npy": _npy_bytes(structured)}, "cloud.npy", ("cloud.npy",))]


def _npz_bytes(compressed: bool, **arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def _seeds_npz(tmp: Path) -> list[Seed]:
    pts = _cloud()
    return [Seed({"scan.npz": _npz_bytes(True, data=pts)}, "scan.npz", ("scan.npz",)),
            Seed({"one.npz": _npz_bytes(False, points=pts)}, "one.npz", ("one.npz",)),
            Seed({"two.npz": _npz_bytes(False, data=pts, extra=np.arange(3))}, "two.npz", ("two.npz",))]


def _seeds_bin(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.scan_folder import write_bin

    write_bin(tmp / "000000.bin", _cloud(), np.linspace(0, 1, 16))
    return [Seed(_written(tmp, ["000000.bin"]), "000000.bin", ("000000.bin",))]


def _seeds_pcd(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.pcd import write_pcd

    pts = _cloud()
    extra = {"intensity": np.linspace(0, 1, 16).astype(np.float32), "ring": np.arange(16, dtype=np.uint16)}
    write_pcd(tmp / "a.pcd", pts, extra, binary=False)
    write_pcd(tmp / "b.pcd", pts, extra, binary=True)
    write_pcd(tmp / "c.pcd", pts, extra, compressed=True)
    write_pcd(tmp / "d.pcd", pts, {"normal": np.ones((16, 3), np.float32)}, width=4, height=4, binary=False)
    return [Seed(_written(tmp, [n]), n, (n,)) for n in ("a.pcd", "b.pcd", "c.pcd", "d.pcd")]


def ply_bytes(points: np.ndarray, fmt: str = "binary_little_endian", faces: bool = False,
              intensity: bool = True) -> bytes:
    """A PLY point cloud written by hand (``ascii``, ``binary_little_endian``, ``binary_big_endian``)."""
    n = len(points)
    props = ["float x", "float y", "float z"] + (["float intensity"] if intensity else [])
    head = ["ply", f"format {fmt} 1.0", "comment written by the dm2 fuzzer", f"element vertex {n}"]
    head += [f"property {p}" for p in props]
    if faces:
        head += ["element face 1", "property list uchar int vertex_indices"]
    head.append("end_header")
    cols = [points[:, 0], points[:, 1], points[:, 2]] + ([np.linspace(0, 1, n)] if intensity else [])
    table = np.column_stack(cols).astype(np.float32)
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table).encode()
        if faces:
            body += b"3 0 1 2\n"
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        body = table.astype(order + "f4").tobytes()
        if faces:
            body += bytes([3]) + np.array([0, 1, 2], order + "i4").tobytes()
    return ("\n".join(head) + "\n").encode() + body


def _seeds_ply(tmp: Path) -> list[Seed]:
    pts = _cloud()
    return [Seed({"a.ply": ply_bytes(pts, "ascii")}, "a.ply", ("a.ply",)),
            Seed({"b.ply": ply_bytes(pts, "binary_little_endian", faces=True)}, "b.ply", ("b.ply",)),
            Seed({"c.ply": ply_bytes(pts, "binary_big_endian", intensity=False)}, "c.ply", ("c.ply",))]


def png_bytes(depth: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(depth.astype(np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def _depth_image(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    d = rng.integers(500, 3000, (12, 16)).astype(np.uint16)
    d[0, :3] = 0
    return d


def _seeds_depth(tmp: Path) -> list[Seed]:
    seven: Files = {"seq/camera-intrinsics.txt": b"585 0 8\n0 585 6\n0 0 1\n"}
    traj = _walk(2, np.random.default_rng(8))
    for k in range(2):
        seven[f"seq/frame-{k:06d}.depth.png"] = png_bytes(_depth_image(k))
        seven[f"seq/frame-{k:06d}.pose.txt"] = "".join(
            " ".join(f"{v:.9f}" for v in row) + "\n" for row in traj.poses[k]).encode()
    tum: Files = {"tum/depth.txt": b"# depth maps\n1.0 depth/1.0.png\n1.5 depth/1.5.png\n",
                  "tum/depth/1.0.png": png_bytes(_depth_image(3)), "tum/depth/1.5.png": png_bytes(_depth_image(4)),
                  "tum/groundtruth.txt": b"1.0 0 0 0 0 0 0 1\n1.49 1 0 0 0 0 0 1\n"}
    return [Seed(seven, "seq", tuple(seven)), Seed(tum, "tum", tuple(tum))]


# --- bags


def _stamp(ts, k: int, frame: str = "lidar"):
    header = ts.types["std_msgs/msg/Header"]
    fields = {"stamp": ts.types["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=250_000_000), "frame_id": frame}
    return header(seq=k, **fields) if "seq" in header.__dataclass_fields__ else header(**fields)


def _pointcloud2(ts, k: int):
    t = ts.types
    pts = np.zeros(4, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    pts["x"], pts["y"], pts["z"], pts["intensity"] = np.arange(4) + k, -np.arange(4), 0.5, 1.0
    fields = [t["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
              for i, n in enumerate(("x", "y", "z", "intensity"))]
    return t["sensor_msgs/msg/PointCloud2"](
        header=_stamp(ts, k), height=1, width=4, fields=fields, is_bigendian=False, point_step=16, row_step=64,
        data=pts.view(np.uint8).reshape(-1), is_dense=True)


def _laserscan(ts, k: int):
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=_stamp(ts, k), angle_min=-1.5, angle_max=1.5, angle_increment=0.5, time_increment=0.001,
        scan_time=0.1, range_min=0.1, range_max=30.0, ranges=np.array([1, 2, 3, 4, 5, 6, 7], np.float32),
        intensities=np.zeros(7, np.float32))


def _tf(ts, k: int):
    t = ts.types
    tr = t["geometry_msgs/msg/TransformStamped"](
        header=_stamp(ts, k, "map"), child_frame_id="base",
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=0.1 * k, y=0.0, z=0.0),
            rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
    return t["tf2_msgs/msg/TFMessage"](transforms=[tr])


_SCAN_TOPICS = {"/points": (_pointcloud2, "sensor_msgs/msg/PointCloud2"),
                "/scan": (_laserscan, "sensor_msgs/msg/LaserScan"), "/tf": (_tf, "tf2_msgs/msg/TFMessage")}
BAG_TOPICS = (None, "/dm2/poses", "/points", "/scan", "/tf:map.base")


def _write_scan_bag(path: Path, ros1: bool, storage=None) -> None:
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=8, **({"storage_plugin": storage} if storage is not None else {}))
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    with writer:
        topics = {t: v for t, v in _SCAN_TOPICS.items() if not (ros1 and t == "/tf")}  # no tf2_msgs in ROS 1 store
        conns = {t: writer.add_connection(t, m, typestore=ts) for t, (_, m) in topics.items()}
        for k in range(3):
            for topic, (make, msgtype) in topics.items():
                writer.write(conns[topic], (100 + k) * 10**9 + 300_000_000, serialize(make(ts, k), msgtype))


def _folder_files(root: Path, folder: Path) -> Files:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _seeds_ros1(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.bag import write
    from dm2_backend.formats.registry import ReadOptions

    write(_walk(5, np.random.default_rng(9)), tmp / "poses.bag", ReadOptions())
    _write_scan_bag(tmp / "scans.bag", ros1=True)
    return [Seed(_written(tmp, ["poses.bag"]), "poses.bag", ("poses.bag",), (None, "/dm2/poses")),
            Seed(_written(tmp, ["scans.bag"]), "scans.bag", ("scans.bag",), BAG_TOPICS[2:4])]


def _seeds_ros2(tmp: Path) -> list[Seed]:
    from dm2_backend.formats.bag import write
    from dm2_backend.formats.registry import ReadOptions

    write(_walk(5, np.random.default_rng(10)), tmp / "posesbag", ReadOptions())
    _write_scan_bag(tmp / "scansbag", ros1=False)
    out = []
    for name, topics in (("posesbag", (None, "/dm2/poses")), ("scansbag", BAG_TOPICS[2:])):
        files = _folder_files(tmp, tmp / name)
        out.append(Seed(files, name, tuple(files), topics))
    return out


def _seeds_mcap(tmp: Path) -> list[Seed]:
    from rosbags.rosbag2 import StoragePlugin

    from dm2_backend.formats.bag import write
    from dm2_backend.formats.registry import ReadOptions

    write(_walk(5, np.random.default_rng(11)), tmp / "poses.mcap", ReadOptions())
    _write_scan_bag(tmp / "scans_mcap", ros1=False, storage=StoragePlugin.MCAP)
    (inner,) = (tmp / "scans_mcap").glob("*.mcap")
    return [Seed(_written(tmp, ["poses.mcap"]), "poses.mcap", ("poses.mcap",), (None, "/dm2/poses")),
            Seed({"scans.mcap": inner.read_bytes()}, "scans.mcap", ("scans.mcap",), BAG_TOPICS[2:])]


def _seeds_config(tmp: Path) -> list[Seed]:
    text = (b"seed: 3\nnproc: 1\nframes:\n  max_points: 512\n  voxel: 0.1\nwarm_start:\n  name: poses\n"
            b"registration:\n  name: icp\n  options: {max_distance: 0.5}\noptimiser:\n  epochs: 5\n  lr: 0.001\n")
    return [Seed({"config.yaml": text}, "config.yaml", ("config.yaml",))]


def _load_config(path: Path) -> None:
    from dm2_backend import config

    config.load(path)


FAMILIES: dict[str, Family] = {f.name: f for f in [
    Family("tum", _seeds_tum),
    Family("kitti", _seeds_kitti),
    Family("euroc", _seeds_euroc),
    Family("g2o", _seeds_g2o),
    Family("carmen", _seeds_carmen),
    Family("carmen_compressed", _seeds_carmen_compressed, kinds={".gz": "gz", ".bz2": "bz2"}),
    Family("dm2_priors", _seeds_priors),
    Family("npy", _seeds_npy, convert=False),
    Family("npz", _seeds_npz, kinds={".npz": "npz"}, convert=False),
    Family("bin", _seeds_bin, convert=False),
    Family("pcd", _seeds_pcd, convert=False),
    Family("ply", _seeds_ply, convert=False),
    Family("depth", _seeds_depth, kinds={".png": "png"}),
    Family("ros1", _seeds_ros1),
    Family("ros2", _seeds_ros2),
    Family("mcap", _seeds_mcap),
    Family("config", _seeds_config, convert=False, custom=_load_config),
]}

_SEED_CACHE: dict[str, list[Seed]] = {}


def seeds(name: str, extra: list[Seed] | None = None) -> list[Seed]:
    """The family's generated seeds (built once per process), plus ``extra``."""
    if name not in _SEED_CACHE:
        with tempfile.TemporaryDirectory(prefix="dm2-seeds-") as tmp:
            _SEED_CACHE[name] = FAMILIES[name].build(Path(tmp))
    return _SEED_CACHE[name] + list(extra or [])


def real_seeds(name: str, data: Path, max_bytes: int = 1 << 20) -> list[Seed]:
    """Seeds from real files in ``../shared/data`` (benchmark only): small files whole; text files cut to
    their first ``max_bytes`` at a line end."""
    picks = {
        "tum": ["trajectories/freiburg1_xyz-groundtruth.txt", "trajectories/fr2_desk_ORB.txt"],
        "kitti": ["trajectories/KITTI_00_gt.txt"],
        "euroc": ["trajectories/V102_groundtruth.csv"],
        "g2o": ["posegraphs/tinyGrid3D.g2o", "posegraphs/intel.g2o"],
        "carmen_compressed": ["carmen/aces-corrected.log.gz"],
        "ros1": ["bags/tf_example.bag"],
        "mcap": ["bags/nav2_turtlebot.mcap"],
    }.get(name, [])
    out = []
    for rel in picks:
        path = data / rel
        if not path.is_file():
            continue
        raw = path.read_bytes()
        if name in ("tum", "kitti", "euroc", "g2o") and len(raw) > max_bytes // 16:
            raw = raw[: raw.rfind(b"\n", 0, max_bytes // 16) + 1]
        if len(raw) > max_bytes:
            continue
        topics = {"ros1": (None, "/tf:map.base_link"), "mcap": (None,)}.get(name, (None,))
        out.append(Seed({path.name: raw}, path.name, (path.name,), topics))
    return out


# ------------------------------------------------------------------------------------------ mutations

NUMBERS = [b"nan", b"NaN", b"inf", b"-inf", b"1e308", b"-1e308", b"1e400", b"0", b"-0", b"-1", b"1e-320",
           b"99999999999999999999999999", b"-99999999999999999999999", b"4294967296", b"2147483648",
           b"18446744073709551616", b"9223372036854775808", b"1.5", b"0.5", b"1e20", b"1e19", b"65535",
           b"0x10", b"1_000", b"", b"abc", b"1e9999999999"]
GARBAGE = [b"\xff\xfe\x80\x81", b"\x00", b"\xc3\x28", b"\r", b"\t", b"#", b",", b"\xe2\x82", b" ", b"\n\n"]
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_WORD = re.compile(rb"[A-Za-z_][A-Za-z0-9_:/.]*")


def _span(rng: np.random.Generator, n: int) -> tuple[int, int]:
    a = int(rng.integers(0, n + 1))
    b = min(n, a + int(rng.geometric(0.05)))
    return a, b


def _lines_op(data: bytes, rng: np.random.Generator) -> bytes:
    lines = data.split(b"\n")
    if not lines:
        return data
    i, j = int(rng.integers(len(lines))), int(rng.integers(len(lines)))
    op = int(rng.integers(9))
    if op == 0:  # delete a line
        del lines[i]
    elif op == 1:  # duplicate a line (duplicated stamps)
        lines.insert(i, lines[i])
    elif op == 2:  # swap two lines (unsorted stamps)
        lines[i], lines[j] = lines[j], lines[i]
    elif op == 3:  # insert a garbage / comment / empty line
        lines.insert(i, [b"", b"# comment", b"garbage line", b"\xff\xfe bytes", b"1 2 3", b"nan " * 8,
                         b" ".join([b"1e308"] * int(rng.integers(1, 40)))][int(rng.integers(7))])
    elif op == 4:  # drop a field (wrong column count)
        words = lines[i].split()
        if words:
            del words[int(rng.integers(len(words)))]
        lines[i] = b" ".join(words)
    elif op == 5:  # add a field
        words = lines[i].split()
        words.insert(int(rng.integers(len(words) + 1)), NUMBERS[int(rng.integers(len(NUMBERS)))] or b"7")
        lines[i] = b" ".join(words)
    elif op == 6:  # the stamp (first number) of line i copied from line j
        wi, wj = lines[i].split(b" ", 1), lines[j].split(b" ", 1)
        if len(wi) == 2 and wj:
            lines[i] = wj[0] + b" " + wi[1]
    elif op == 7:  # reverse the order of all lines
        lines.reverse()
    else:  # commas for spaces or the other way round
        lines[i] = lines[i].replace(b" ", b",") if rng.random() < 0.5 else lines[i].replace(b",", b" ")
    return b"\n".join(lines)


def mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """One random mutation of ``data``."""
    n = len(data)
    op = int(rng.integers(12))
    if op == 0:  # truncate
        return data[: int(rng.integers(0, n + 1))]
    if op == 1 and n:  # flip bytes
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 9))):
            b[int(rng.integers(n))] ^= int(rng.integers(1, 256))
        return bytes(b)
    if op == 2:  # insert random or garbage bytes
        pos = int(rng.integers(0, n + 1))
        ins = GARBAGE[int(rng.integers(len(GARBAGE)))] if rng.random() < 0.5 else rng.bytes(int(rng.integers(1, 32)))
        return data[:pos] + ins + data[pos:]
    if op == 3:  # delete a range
        a, b = _span(rng, n)
        return data[:a] + data[b:]
    if op == 4:  # duplicate a range
        a, b = _span(rng, n)
        return data[:b] + data[a:b] + data[b:]
    if op in (5, 6):  # a number replaced by NaN / inf / huge / odd text
        matches = list(_NUMBER.finditer(data[:65536]))
        if matches:
            m = matches[int(rng.integers(len(matches)))]
            return data[: m.start()] + NUMBERS[int(rng.integers(len(NUMBERS)))] + data[m.end():]
    if op == 7 and b"\n" in data[:4096]:
        return _lines_op(data, rng)
    if op == 8:  # an overlong token
        matches = list(_WORD.finditer(data[:4096]))
        if matches:
            m = matches[int(rng.integers(len(matches)))]
            return data[: m.end()] + b"A" * int(rng.choice([300, 5000, 70000])) + data[m.end():]
    if op == 9:  # a word replaced by non-UTF-8 bytes
        matches = list(_WORD.finditer(data[:4096]))
        if matches:
            m = matches[int(rng.integers(len(matches)))]
            return data[: m.start()] + b"\xff\xfe" + data[m.start() + 1:]
    if op == 10:
        return b"" if rng.random() < 0.3 else data[: int(rng.integers(0, min(n, 64) + 1))]
    if op == 11 and n:  # set a little-endian integer somewhere to a huge / zero value
        pos = int(rng.integers(0, max(n - 8, 1)))
        word = struct.pack("<Q", int(rng.choice([0, 2**31, 2**32 - 1, 2**40, 2**63 - 1])))
        return data[:pos] + word[: min(8, n - pos)] + data[pos + 8:]
    return _lines_op(data, rng) if b"\n" in data else data[: n // 2]


def _png_chunks(data: bytes) -> list[list] | None:
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return None
    chunks, pos = [], 8
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        chunks.append([kind, data[pos + 8:pos + 8 + length]])
        pos += 12 + length
    return chunks


def _png_join(chunks: list[list]) -> bytes:
    out = b"\x89PNG\r\n\x1a\n"
    for kind, body in chunks:
        out += struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    return out


def _mutate_png(data: bytes, rng: np.random.Generator) -> bytes:
    chunks = _png_chunks(data)
    if not chunks:
        return mutate_bytes(data, rng)
    op = int(rng.integers(4))
    if op == 0 and chunks[0][0] == b"IHDR":  # declared size (decompression bomb)
        w, h = (int(rng.choice([0, 1, 4, 100_000, 1_000_000, 2**31 - 1])) for _ in range(2))
        chunks[0][1] = struct.pack(">II", w, h) + chunks[0][1][8:]
    elif op == 1:  # a chunk's body changed, CRC fixed
        k = int(rng.integers(len(chunks)))
        chunks[k][1] = mutate_bytes(chunks[k][1], rng)
    elif op == 2:  # IDAT: valid zlib of wrong content
        for c in chunks:
            if c[0] == b"IDAT":
                try:
                    c[1] = zlib.compress(mutate_bytes(zlib.decompress(c[1]), rng)) if rng.random() < 0.5 else c[1][:-4]
                except zlib.error:
                    c[1] = c[1][:-4]
    else:  # a chunk duplicated or dropped
        k = int(rng.integers(len(chunks)))
        chunks.insert(k, chunks[k]) if rng.random() < 0.5 else chunks.pop(k)
    return _png_join(chunks)


def _mutate_npz(data: bytes, rng: np.random.Generator) -> bytes:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            if any(i.file_size > 1 << 20 for i in zf.infolist()):
                return mutate_bytes(data, rng)
            members = [(i.filename, zf.read(i.filename), i.compress_type) for i in zf.infolist()]
    except Exception:  # the fuzzer's own unpacking of an already-mutated zip: any failure, mutate the bytes
        return mutate_bytes(data, rng)
    k = int(rng.integers(len(members))) if members else 0
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i, (name, body, how) in enumerate(members):
            if i == k:
                body = mutate_bytes(body, rng) if rng.random() < 0.7 else _mutate_npy_header(body, rng)
            zf.writestr(name, body, compress_type=how)
    return buf.getvalue()


_NPY_DESCRS = [b"'<f4'", b"'|O'", b"'<U8'", b"'|S4'", b"'<f8'", b"[('x', '<f4'), ('y', '<U3')]", b"'<c16'",
               b"[('x', '<f4', (2,)), ('y', '<f4'), ('z', '<f4')]", b"'>f4'", b"'|b1'", b"'<M8[s]'", b"'|V4'",
               b"[('x', 'O')]", b"'<f2'", b"'<i8'", b"[('x','<f4'),('y','<f4'),('z','<f4'),('s','<U4')]"]
_NPY_SHAPES = [b"()", b"(0,)", b"(0, 3)", b"(3,)", b"(16, 4)", b"(16, 6)", b"(4294967296, 4)", b"(3000000000000, 1000)",
               b"(-1, 3)", b"(16, 2)", b"(2, 2, 2, 2)", b"(16,)", b"(6, 6)", b"(6, 2, 6)"]


def _mutate_npy_header(data: bytes, rng: np.random.Generator) -> bytes:
    """Change the dtype, shape or order declared in an .npy header (the body kept)."""
    if not data.startswith(b"\x93NUMPY") or len(data) < 10:
        return mutate_bytes(data, rng)
    major = data[6]
    hlen_size = 2 if major == 1 else 4
    hlen = int.from_bytes(data[8:8 + hlen_size], "little")
    start = 8 + hlen_size
    header = data[start:start + hlen]
    op = int(rng.integers(3))
    if op == 0:
        header = re.sub(rb"'descr': [^,]*(?:\]|')", b"'descr': " + _NPY_DESCRS[int(rng.integers(len(_NPY_DESCRS)))],
                        header, count=1)
    elif op == 1:
        header = re.sub(rb"'shape': \([^)]*\)", b"'shape': " + _NPY_SHAPES[int(rng.integers(len(_NPY_SHAPES)))],
                        header, count=1)
    else:
        cut = int(rng.integers(len(header) + 1))
        header = header.replace(b"False", b"True") if rng.random() < 0.5 else header[:cut]
    header = header.rstrip(b"\n ")
    pad = (-(start + len(header) + 1)) % 64
    header = header + b" " * pad + b"\n"
    if len(header) >= 1 << (8 * hlen_size):
        return data
    return data[:start - hlen_size] + len(header).to_bytes(hlen_size, "little") + header + data[start + hlen:]


def mutate_file(name: str, data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """One mutation of one file, structure-aware by ``kind`` half of the time (plain bytes when the file is
    already too broken for the structure-aware mutation)."""
    try:
        return _mutate_file(name, data, kind, rng)
    except Exception:  # the fuzzer's own parsing of a mutated input; never the code under test
        return mutate_bytes(data, rng)


def _mutate_file(name: str, data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    aware = rng.random() < 0.5
    if kind == "gz" and aware:
        try:
            return gzip.compress(mutate_bytes(gzip.decompress(data), rng), mtime=0)
        except (OSError, EOFError, zlib.error):
            pass
    if kind == "bz2" and aware:
        try:
            return bz2.compress(mutate_bytes(bz2.decompress(data), rng))
        except (OSError, EOFError, ValueError):
            pass
    if kind == "npz" and aware:
        return _mutate_npz(data, rng)
    if kind == "png" and aware:
        return _mutate_png(data, rng)
    if name.endswith(".npy") and aware and rng.random() < 0.5:
        return _mutate_npy_header(data, rng)
    return mutate_bytes(data, rng)


def _kind_of(family: Family, name: str) -> str:
    for suffix, kind in family.kinds.items():
        if name.endswith(suffix):
            return kind
    return "binary"


def mutate(family: Family, seed: Seed, rng: np.random.Generator) -> Files:
    """A mutated copy of ``seed``: 1 to ~4 stacked mutations, each on one target file."""
    files = dict(seed.files)
    for _ in range(min(int(rng.geometric(0.5)), 4)):
        target = seed.targets[int(rng.integers(len(seed.targets)))]
        files[target] = mutate_file(target, files[target], _kind_of(family, target), rng)
    return files


def make_input(name: str, index: int, base_seed: int = 0, extra: list[Seed] | None = None
               ) -> tuple[Files, str, str | None]:
    """Input ``index`` of family ``name``: (files, entry, topic); deterministic in (base_seed, index)."""
    family = FAMILIES[name]
    pool = seeds(name, extra)
    rng = np.random.default_rng([base_seed, index, sum(name.encode())])
    seed = pool[int(rng.integers(len(pool)))]
    topic = seed.topics[int(rng.integers(len(seed.topics)))]
    files = dict(seed.files) if index % 50 == 0 else mutate(family, seed, rng)  # every 50th: the seed itself
    return files, seed.entry, topic


# ------------------------------------------------------------------------------------------- oracle


@dataclass
class Outcome:
    kind: str  # "read", "error", or a failure kind
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.kind in ("read", "error")


def materialise(files: Files, root: Path) -> None:
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _finite_rows(rows: list[tuple[str, str]]) -> str | None:
    for key, value in rows:
        if key == "messages" or key.startswith("topic"):  # names from the file (a message called "nan")
            continue
        words = re.findall(r"[a-z]+", value.lower())
        if "nan" in words or "inf" in words:
            return f"{key}: {value}"
    return None


def _clean_error(exc: BaseException, entry: Path) -> Outcome:
    if isinstance(exc, InputError):
        msg = exc.message
    else:  # the OS errors the CLI prints as "filename: strerror"
        msg = f"{exc.filename}: {exc.strerror}"
    if "\n" in msg or "\r" in msg:
        return Outcome("multi-line", msg[:300])
    if str(entry) not in msg:
        return Outcome("unnamed", msg[:300])
    return Outcome("error", msg[:200])


CLEAN = (InputError, FileNotFoundError, IsADirectoryError, PermissionError)


def _run(family: Family, entry: Path, topic: str | None, out: Path) -> Outcome:
    from dm2_backend.cli.info import describe
    from dm2_backend.formats import ReadOptions, read_trajectory, write_trajectory

    if family.custom is not None:
        family.custom(entry)
        return Outcome("read")
    options = ReadOptions(topic=topic)
    rows = describe(entry, None, options)
    bad = _finite_rows(rows)
    if bad:
        return Outcome("non-finite", bad[:300])
    if not family.convert:
        return Outcome("read")
    traj = read_trajectory(entry, None, options)
    if not np.isfinite(traj.poses).all() or (traj.timestamps is not None and not np.isfinite(traj.timestamps).all()):
        return Outcome("non-finite", "trajectory poses or stamps")
    dst = out / "out.txt"
    write_trajectory(traj, dst, "tum")
    try:
        back = read_trajectory(dst, "tum")
    except InputError as exc:
        return Outcome("read-back", exc.message[:300])
    if len(back) != len(traj):
        return Outcome("read-back", f"{len(back)} poses read back for {len(traj)}")
    return Outcome("read")


def check(name: str, files: Files, entry: str, topic: str | None, work: Path) -> Outcome:
    """Materialise the input under ``work`` and run the oracle; ``work`` is emptied afterwards."""
    family = FAMILIES[name]
    inp, out = work / "in", work / "out"
    shutil.rmtree(work, ignore_errors=True)
    inp.mkdir(parents=True)
    out.mkdir()
    materialise(files, inp)
    before = _listing(inp)
    path = inp / entry
    t0 = time.perf_counter()
    try:
        outcome = _run(family, path, topic, out)
    except CLEAN as exc:
        outcome = _clean_error(exc, path)
    except MemoryError as exc:
        outcome = Outcome("memory", str(exc)[:200])
    except RecursionError as exc:
        outcome = Outcome("exception:RecursionError", str(exc)[:200])
    except Exception as exc:  # the oracle counts every other exception as a failure of its kind
        outcome = Outcome(f"exception:{type(exc).__name__}", f"{exc}"[:300])
    elapsed = time.perf_counter() - t0
    if outcome.ok and elapsed > SLOW_S:
        outcome = Outcome("slow", f"{elapsed:.1f} s")
    if outcome.ok:
        left = sorted((_listing(inp) - before) | {n for n in _listing(out) if n != "out.txt" or
                                                  outcome.kind != "read"})
        left += sorted(str(p) for p in work.parent.glob(".tmp-*"))
        if left:
            outcome = Outcome("leftover", ", ".join(left)[:300])
    shutil.rmtree(work, ignore_errors=True)
    return outcome


def run_family(name: str, count: int | None = None, seconds: float | None = None, base_seed: int = 0,
               work: Path | None = None, extra: list[Seed] | None = None) -> dict:
    """In-process run over inputs 0, 1, ... until ``count`` inputs or ``seconds`` elapsed; a summary dict
    with counts and the failures (index, kind, detail)."""
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="dm2-fuzz-")) if own else work
    stats = {"family": name, "inputs": 0, "clean_errors": 0, "clean_reads": 0, "failures": {}, "examples": []}
    t0 = time.perf_counter()
    i = 0
    try:
        while (count is None or i < count) and (seconds is None or time.perf_counter() - t0 < seconds):
            files, entry, topic = make_input(name, i, base_seed, extra)
            outcome = check(name, files, entry, topic, work / "case")
            record(stats, i, outcome)
            i += 1
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)
    return stats


def record(stats: dict, index: int, outcome: Outcome) -> None:
    stats["inputs"] += 1
    if outcome.kind == "read":
        stats["clean_reads"] += 1
    elif outcome.kind == "error":
        stats["clean_errors"] += 1
    else:
        stats["failures"][outcome.kind] = stats["failures"].get(outcome.kind, 0) + 1
        if sum(1 for e in stats["examples"] if e["kind"] == outcome.kind) < 3:
            stats["examples"].append({"index": index, "kind": outcome.kind, "detail": outcome.detail})


def summary_json(results: list[dict]) -> str:
    return json.dumps(results, indent=1, default=lambda o: o if not isinstance(o, float) or math.isfinite(o)
                      else str(o))
