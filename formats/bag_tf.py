"""TF chains from bags, looked up as evo's ``TfCache`` does with tf2 (without a ROS install).

An id ``/tf:parent.child`` (optionally ``:/static_topic``, default ``/tf_static``) names the pose of
``child`` in ``parent``. As in evo: poses are looked up every 0.1 s (integer nanoseconds) from the stamp
of the first transform on the TF topic up to the latest time common to the chain's links; a time
outside a link's data is skipped; links are interpolated as tf2 does (linear translation, shortest-path
slerp, ratio from nanosecond differences); the first transform of a repeated stamp is kept; data older
than the newest minus 10000 s (evo's buffer length) is dropped.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from dm2_backend.formats.bag_messages import bad_quaternion, split_ns, stamp_ns
from dm2_backend.kernel.geometry import se3

_ROS_NAME = re.compile(r"[\/|a-z|A-Z][\/|_|0-9|a-z|A-Z]+")  # evo's tf_id.ROS_NAME_REGEX
LOOKUP_STEP_NS = 100_000_000  # evo's default tf_cache_lookup_frequency, 10 Hz
BUFFER_NS = 10_000 * 1_000_000_000  # evo's default tf_cache_max_time, 10000 s


@dataclass(frozen=True)
class TfId:
    topic: str
    parent: str
    child: str
    static_topic: str = "/tf_static"


def parse_tf_id(identifier: str) -> TfId | None:
    """``/tf:parent.child[:/tf_static]`` split as evo's ``tf_id.split_id``; None when not such an id."""
    topic, _, rest = identifier.partition(":")
    static = "/tf_static"
    if ":" in rest:
        rest, _, static = rest.rpartition(":")
        if _ROS_NAME.match(static) is None:
            return None
    parent, _, child = rest.partition(".")
    if _ROS_NAME.match(topic) is None or not parent or not child:
        return None
    return TfId(topic, parent, child, static)


class TfError(ValueError):
    """A chain that cannot be looked up; the message names the frames."""


@dataclass
class _Link:
    parents: list[str] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)
    xyz: list[tuple] = field(default_factory=list)
    quat: list[tuple] = field(default_factory=list)


class TfBuffer:
    """Transforms of one TF topic (plus its static topic), keyed by child frame."""

    def __init__(self) -> None:
        self.dynamic: dict[str, _Link] = {}
        self.static: dict[str, tuple[str, tuple, tuple]] = {}
        self.start_ns: int | None = None

    def add(self, msg, static: bool) -> None:
        """Add a tf2_msgs/TFMessage (dynamic topic first, then static, as evo loads them)."""
        for tf in msg.transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            xyz, quat = (t.x, t.y, t.z), (q.x, q.y, q.z, q.w)
            child, parent = tf.child_frame_id, tf.header.frame_id
            if not static and self.start_ns is None:
                self.start_ns = stamp_ns(tf.header.stamp)
            if static and child not in self.dynamic:
                self.static[child] = (parent, xyz, quat)
                continue
            link = self.dynamic.setdefault(child, _Link())
            link.parents.append(parent)
            link.stamps.append(stamp_ns(tf.header.stamp))
            link.xyz.append(xyz)
            link.quat.append(quat)

    @property
    def frames(self) -> list[str]:
        parents = {p for link in self.dynamic.values() for p in link.parents}
        parents |= {p for p, _, _ in self.static.values()}
        return sorted(set(self.dynamic) | set(self.static) | parents)

    def _parent(self, frame: str) -> str | None:
        if frame in self.dynamic:
            parents = set(self.dynamic[frame].parents)
            if len(parents) > 1:
                names = ", ".join(sorted(parents))
                raise TfError(f"frame {frame!r} has several parents ({names}); tf needs a tree")
            return parents.pop()
        return self.static[frame][0] if frame in self.static else None

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while (parent := self._parent(path[-1])) is not None:
            if parent in path:
                raise TfError(f"frames {' -> '.join(path + [parent])} form a loop")
            path.append(parent)
        return path

    def chain(self, parent: str, child: str) -> tuple[list[str], list[str]]:
        """Frames below the common ancestor on the way up from ``child`` and from ``parent``."""
        known = self.frames
        for frame in (parent, child):
            if frame not in known:
                raise TfError(f"frame {frame!r} is not in the TF data (frames: {', '.join(known)})")
        if parent == child:
            raise TfError(f"parent and child are the same frame {parent!r}")
        up_child, up_parent = self._path_to_root(child), self._path_to_root(parent)
        common = next((f for f in up_child if f in up_parent), None)
        if common is None:
            raise TfError(f"frames {parent!r} and {child!r} are not connected")
        return up_child[: up_child.index(common)], up_parent[: up_parent.index(common)]

    def _link_arrays(self, frame: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        link = self.dynamic[frame]
        stamps = np.asarray(link.stamps, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        keep = np.ones(len(stamps), bool)
        keep[1:] = stamps[1:] != stamps[:-1]  # tf2 ignores repeated stamps (first one wins)
        keep &= stamps >= stamps[-1] - BUFFER_NS
        idx = order[keep]
        xyz, quat = np.asarray(link.xyz, np.float64)[idx], np.asarray(link.quat, np.float64)[idx]
        if bad_quaternion(quat).any():
            i = int(np.argmax(bad_quaternion(quat)))
            at, q = stamps[keep][i], quat[i].tolist()
            raise TfError(f"transform {link.parents[0]} -> {frame} at {at} ns has quaternion {q}")
        return stamps[keep], xyz, quat

    def _link_poses(self, frame: str, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses (M,4,4) of ``frame`` in its parent at ``times`` (ns) and the mask of times with data."""
        if frame not in self.dynamic:
            _, xyz, quat = self.static[frame]
            if bad_quaternion(np.asarray(quat)):
                raise TfError(f"static transform of {frame} has quaternion {quat}")
            pose = se3.from_xyz_quat(np.asarray(xyz), np.asarray(quat), "xyzw")
            return np.broadcast_to(pose, (len(times), 4, 4)), np.ones(len(times), bool)
        stamps, xyz, quat = self._link_arrays(frame)
        ok = (times >= stamps[0]) & (times <= stamps[-1])
        poses = np.tile(np.eye(4), (len(times), 1, 1))
        if len(stamps) == 1:
            poses[ok] = se3.from_xyz_quat(xyz[0], quat[0], "xyzw")
            return poses, ok
        rel = (stamps - stamps[0]).astype(np.float64)
        t = (times[ok] - stamps[0]).astype(np.float64)
        poses[ok] = se3.interpolate(rel, se3.from_xyz_quat(xyz, quat, "xyzw"), t)
        return poses, ok

    def trajectory(self, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
        """Poses (N,4,4) of ``child`` in ``parent`` and their stamps (seconds), as evo looks them up."""
        down_child, down_parent = self.chain(parent, child)
        dynamic = [f for f in down_child + down_parent if f in self.dynamic]
        latest = min((self._link_arrays(f)[0][-1] for f in dynamic), default=0)
        start = self.start_ns if self.start_ns is not None else latest
        if latest < start:
            times = np.array([latest], dtype=np.int64)
        else:
            times = np.arange(start, latest + 1, LOOKUP_STEP_NS, dtype=np.int64)
        ok = np.ones(len(times), bool)
        sides = []
        for frames in (down_child, down_parent):
            pose = np.tile(np.eye(4), (len(times), 1, 1))
            for frame in reversed(frames):  # ancestor first
                link, valid = self._link_poses(frame, times)
                pose, ok = pose @ link, ok & valid
            sides.append(pose)
        poses = se3.inverse(sides[1][ok]) @ sides[0][ok]
        secs = [s + n * 1e-9 for s, n in map(split_ns, times[ok].tolist())]
        return poses, np.asarray(secs, dtype=np.float64)
