"""ROS message conversions for the bag adapter: poses, PointCloud2 / LaserScan scans, and the pose
message written back (rosbags message objects; no ROS install)."""

from __future__ import annotations

import numpy as np

from dm2_backend.kernel.scans import Scan

#: pose-carrying message types read as trajectories (the ones evo reads, less PointStamped)
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
)
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
LASERSCAN = "sensor_msgs/msg/LaserScan"
SCAN_TYPES = (POINTCLOUD2, LASERSCAN)
TF_TYPE = "tf2_msgs/msg/TFMessage"
WRITE_TYPE = "geometry_msgs/msg/PoseStamped"

#: a quaternion whose norm is further than this from 1 is rejected (tf2 uses the same bound)
QUAT_NORM_TOL = 0.01

# sensor_msgs/PointField datatype codes -> numpy type
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_TIME_FIELDS = ("time", "t", "timestamp")


def stamp_seconds(stamp) -> float:
    """A header stamp in seconds, computed exactly as evo does: ``sec + nanosec * 1e-9``."""
    return stamp.sec + (stamp.nanosec * 1e-9)


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def split_ns(ns: int) -> tuple[int, int]:
    return ns // 1_000_000_000, ns % 1_000_000_000


def seconds_to_sec_nsec(t: float) -> tuple[int, int]:
    """Seconds (float64) to (sec, nanosec) without going through a float nanosecond count."""
    sec = int(np.floor(t))
    nsec = int(round((t - sec) * 1e9))
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return sec, nsec


def pose_of(msg) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """Position and xyzw quaternion of a PoseStamped / PoseWithCovarianceStamped / Odometry /
    TransformStamped message."""
    if hasattr(msg, "transform"):
        t, q = msg.transform.translation, msg.transform.rotation
        return (t.x, t.y, t.z), (q.x, q.y, q.z, q.w)
    pose = msg.pose
    while not hasattr(pose, "position"):  # Odometry / PoseWithCovariance nest a Pose
        pose = pose.pose
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


def bad_quaternion(q: np.ndarray) -> np.ndarray:
    """Mask of quaternions (N,4) that are not finite or not of unit norm within :data:`QUAT_NORM_TOL`."""
    norm = np.linalg.norm(q, axis=-1)
    return ~np.isfinite(norm) | (np.abs(norm - 1.0) > QUAT_NORM_TOL)


def pointcloud2_scan(msg) -> Scan:
    """Points (x, y, z), and intensity, per-point time and ring when present; non-finite points dropped.

    Integer time fields are taken as nanoseconds (Ouster ``t``) and converted to seconds; float time
    fields are kept as stored (seconds). Raises ``ValueError`` for layouts it cannot read.
    """
    fields = {f.name: f for f in msg.fields}
    if missing := [n for n in "xyz" if n not in fields]:
        have = ", ".join(fields) or "none"
        raise ValueError(f"PointCloud2 has no field {'/'.join(missing)} (fields: {have})")
    time_name = next((n for n in _TIME_FIELDS if n in fields), None)
    names = ["x", "y", "z"] + [n for n in ("intensity", time_name, "ring") if n in fields]
    step = int(msg.point_step)
    formats = []
    for name in names:
        f = fields[name]
        if f.datatype not in _POINTFIELD_TYPES:
            raise ValueError(f"PointCloud2 field {name!r} has unknown datatype {f.datatype}")
        fmt = np.dtype(_POINTFIELD_TYPES[f.datatype]).newbyteorder(">" if msg.is_bigendian else "<")
        if f.offset + fmt.itemsize > step:
            raise ValueError(f"PointCloud2 field {name!r} at offset {f.offset} overruns point_step {step}")
        formats.append(fmt)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": [fields[n].offset for n in names],
                      "itemsize": step})
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    need = (height - 1) * row_step + width * step if height else 0
    if step <= 0 or row_step < width * step or len(data) < need:
        raise ValueError(
            f"PointCloud2 data holds {len(data)} bytes, expected {height} rows of {row_step} "
            f"(width {width}, point_step {step})"
        )
    data = np.pad(data[: height * row_step], (0, max(0, height * row_step - len(data))))
    rows = data.reshape(height, row_step)[:, : width * step]
    cloud = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    keep = np.isfinite(xyz).all(axis=1)
    intensity = cloud["intensity"][keep].astype(np.float32) if "intensity" in names else None
    ring = cloud["ring"][keep].astype(np.int32) if "ring" in names else None
    point_time = None
    if time_name is not None:
        raw = cloud[time_name][keep]
        point_time = raw * 1e-9 if raw.dtype.kind in "iu" else raw.astype(np.float64)
    return Scan(
        points=xyz[keep], timestamp=stamp_seconds(msg.header.stamp),
        intensity=intensity, point_time=point_time, ring=ring,
    )


def laserscan_scan(msg) -> Scan:
    """LaserScan ranges as 2D points (z = 0) in the sensor frame; inf/NaN/out-of-range readings dropped.
    ``point_time`` is the per-beam offset ``i * time_increment`` (seconds)."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    i = np.arange(len(ranges))
    angles = msg.angle_min + i * msg.angle_increment
    keep = np.isfinite(ranges) & (ranges >= msg.range_min) & (ranges <= msg.range_max)
    r, a = ranges[keep], angles[keep]
    points = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)], axis=1)
    inten = np.asarray(msg.intensities, dtype=np.float32)
    return Scan(
        points=points, timestamp=stamp_seconds(msg.header.stamp),
        intensity=inten[keep] if len(inten) == len(ranges) else None,
        point_time=i[keep] * float(msg.time_increment) if msg.time_increment else None,
    )


def scan_of(msg, msgtype: str) -> Scan:
    return pointcloud2_scan(msg) if msgtype == POINTCLOUD2 else laserscan_scan(msg)


def pose_stamped(typestore, sec: int, nsec: int, xyz, quat_xyzw, frame_id: str, seq: int):
    """A geometry_msgs/PoseStamped of ``typestore`` (ROS 1 headers get ``seq``)."""
    t = typestore.types
    header_type = t["std_msgs/msg/Header"]
    header = {"stamp": t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), "frame_id": frame_id}
    if "seq" in header_type.__dataclass_fields__:
        header["seq"] = seq
    x, y, z = (float(v) for v in xyz)
    qx, qy, qz, qw = (float(v) for v in quat_xyzw)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return t[WRITE_TYPE](header=header_type(**header), pose=pose)
