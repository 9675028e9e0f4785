"""ROS bags through rosbags (no ROS install): ROS 1 ``.bag``, ROS 2 folders (sqlite3 or mcap, with
metadata.yaml), bare ``.db3`` and ``.mcap`` files.

Trajectories come from PoseStamped / PoseWithCovarianceStamped / Odometry / TransformStamped topics, or
from a TF chain named as evo names it (``/tf:parent.child``); stamps are header stamps. Scans come from
PointCloud2 and LaserScan topics, indexed first and deserialised on access. Trajectories are written as
geometry_msgs/PoseStamped.
"""

from __future__ import annotations

import bz2
import contextlib
import functools
import os
import sqlite3
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path

import apsw
import lz4.frame
import numpy as np
import yaml
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as ReaderError1
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag1 import reader as _reader1
from rosbags.rosbag2 import ReaderError as ReaderError2
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2 import storage_mcap as _storage_mcap
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

try:
    from compression import zstd as _zstd  # Python 3.14
except ImportError:  # pragma: no cover - the backport rosbags depends on before 3.14
    from backports import zstd as _zstd

from dm2_backend.formats import bag_messages as bm
from dm2_backend.formats.bag_tf import TfBuffer, TfError, TfId, parse_tf_id
from dm2_backend.formats.registry import (
    ReadOptions,
    ScanSource,
    TrajectoryFormat,
    scan_source,
    trajectory_format,
)
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_path, temp_prefix
from dm2_backend.runtime.errors import InputError

DEFAULT_WRITE_TOPIC = "/dm2/poses"
SUFFIXES = (".bag", ".db3", ".mcap")
_READ_ERRORS = (
    AnyReaderError, ReaderError1, ReaderError2, SerdeError, sqlite3.DatabaseError, apsw.Error, struct.error,
    EOFError,
)
#: largest decompressed chunk accepted from a bag (ROS 1 bz2/lz4 chunks, MCAP lz4/zstd chunks)
MAX_CHUNK_BYTES = 1 << 30


def _bounded(kind: str, data: bytes, limit: int, error: type[Exception]) -> bytes:
    """Decompress ``data`` to at most ``limit`` bytes; library errors and larger outputs become ``error``."""
    try:
        if kind == "lz4":
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=limit + 1)
        elif kind == "zstd":
            out = _zstd.ZstdDecompressor().decompress(data, max_length=limit + 1)
        else:
            out = bz2.BZ2Decompressor().decompress(data, max_length=limit + 1)
    except (RuntimeError, OSError, EOFError, ValueError, _zstd.ZstdError) as exc:
        raise error(f"corrupt {kind} chunk: {exc}") from None
    if len(out) > limit:
        raise error(f"a {kind} chunk decompresses to more than {limit} bytes")
    return out


def _mcap_decompressor(kind: str):
    def run(data: bytes, size: int) -> bytes:
        if size > MAX_CHUNK_BYTES:
            raise ReaderError2(f"a {kind} chunk declares {size} bytes (limit {MAX_CHUNK_BYTES})")
        return _bounded(kind, data, size, ReaderError2)

    return run


# rosbags decompresses chunks without a bound and lets the codecs' own errors through: give it ours
_storage_mcap.DECOMPRESSORS.update({k: _mcap_decompressor(k) for k in ("lz4", "zstd")})
_reader1.decompressors.update({
    k: functools.partial(_bounded, k, limit=MAX_CHUNK_BYTES, error=ReaderError1) for k in ("bz2", "lz4")
})


def _kind(path: Path) -> str:
    if path.is_dir():
        try:
            meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            return f"ROS 2 bag folder ({meta['storage_identifier']})"
        except (OSError, ValueError, yaml.YAMLError, KeyError, TypeError):  # ValueError: not UTF-8
            return "ROS 2 bag folder"
    return {".bag": "ROS 1 bag", ".db3": "ROS 2 sqlite3 file", ".mcap": "ROS 2 mcap file"}.get(
        path.suffix.lower(), "bag"
    )


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[AnyReader]:
    """An open AnyReader; failures to open become :class:`InputError`."""
    reader = None
    try:
        reader = AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
        # the index and metadata are parsed lazily: make rosbags read them here, inside this guard
        _ = reader.topics, reader.message_count, reader.duration, reader.connections
    except Exception as exc:  # rosbags raises many kinds on foreign or truncated files
        if reader is not None:
            with contextlib.suppress(Exception):
                reader.close()
        raise InputError(path, f"cannot open as a {_kind(Path(path))}: {exc}") from None
    try:
        yield reader
    except _READ_ERRORS as exc:
        raise InputError(path, f"cannot read the {_kind(Path(path))}: {exc}") from None
    finally:
        reader.close()


def _messages(reader: AnyReader, **kwargs) -> Iterator:
    """``reader.messages(**kwargs)``; rosbags checks a ROS 1 bag's index against its records with ``assert``,
    which is turned into its reader error here (only around rosbags' own iteration)."""
    it = reader.messages(**kwargs)
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except _READ_ERRORS:
            raise
        except Exception as exc:  # only rosbags runs here; on corrupt records it fails with assert, KeyError...
            raise ReaderError1(f"corrupt bag record ({type(exc).__name__}: {exc})") from None
        yield item


@functools.lru_cache(maxsize=2)
def _standard_stores() -> tuple:
    return get_typestore(Stores.ROS2_HUMBLE), get_typestore(Stores.ROS1_NOETIC)


def _nested(fields) -> Iterator[str]:
    for _, (kind, detail) in fields:
        while isinstance(detail, tuple) and detail and isinstance(detail[0], tuple):  # sequences / arrays
            kind, detail = detail[0]
        if isinstance(detail, str):
            yield detail


def _definition_problem(typestore, msgtype: str) -> str | None:
    """How the bag's own definition of a message type dm2 reads (and of the types inside it) differs from
    ROS's (ROS 2 Humble or ROS 1 Noetic): a corrupt definition deserialises to objects without the fields
    dm2 reads. None when it is the standard one."""
    todo, seen = [msgtype], set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        mine = typestore.fielddefs.get(name)
        if mine is None:
            return f"the bag carries no definition of {name[:80]}"
        if not any(store.fielddefs.get(name) == mine for store in _standard_stores()):
            return f"the bag's definition of {name[:80]} is not the standard one"
        todo.extend(_nested(mine[1]))
    return None


def _deserialize(reader: AnyReader, raw: bytes, msgtype: str):
    """``reader.deserialize`` of a type dm2 reads; a message whose bytes or type definition are corrupt is a
    read error (the generated deserialisers fail with struct, index, key or unicode errors)."""
    checked = reader.__dict__.setdefault("_dm2_checked_types", {})
    if msgtype not in checked:
        checked[msgtype] = _definition_problem(reader.typestore, msgtype)
    if checked[msgtype] is not None:
        raise SerdeError(checked[msgtype])
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as exc:  # only rosbags' generated code runs here
        raise SerdeError(f"cannot deserialise a {msgtype[:80]} message ({type(exc).__name__}: {exc})") from None


def _topic_list(reader: AnyReader) -> str:
    topics = sorted(reader.topics.items())
    return ", ".join(f"{t} ({i.msgtype or 'mixed types'})" for t, i in topics) or "none"


def _pick_topic(reader: AnyReader, path: Path, topic: str | None, types: tuple[str, ...], what: str) -> str:
    """``topic`` checked against the bag, or the only topic of one of ``types``."""
    topics = reader.topics
    if topic is None:
        fits = sorted(t for t, i in topics.items() if i.msgtype in types and i.msgcount > 0)
        if len(fits) == 1:
            return fits[0]
        if not fits:
            tf = "/tf" in topics and what == "poses"
            hint = "; a TF chain is read with --topic /tf:PARENT.CHILD" if tf else ""
            raise InputError(path, f"no topic with {what}; topics: {_topic_list(reader)}{hint}")
        raise InputError(path, f"several topics with {what} ({', '.join(fits)}); say which with --topic")
    if topic not in topics:
        raise InputError(path, f"no topic {topic!r}; topics: {_topic_list(reader)}")
    msgtype = topics[topic].msgtype
    if msgtype not in types:
        short = ", ".join(t.replace("/msg/", "/") for t in types)
        hint = "; a TF chain is read as /tf:PARENT.CHILD" if msgtype == bm.TF_TYPE and what == "poses" else ""
        raise InputError(path, f"type {msgtype} does not hold {what} (readable: {short}){hint}", topic=topic)
    if topics[topic].msgcount == 0:
        raise InputError(path, "no messages", topic=topic)
    if msgtype not in reader.typestore.fielddefs:
        raise InputError(path, f"the bag carries no definition of {msgtype}", topic=topic)
    return topic


def _checked(path: Path, topic: str, traj: Trajectory) -> Trajectory:
    try:
        return traj.validate(path)
    except InputError as err:
        raise InputError(path, err.problem, topic=topic) from None


def _read_tf(reader: AnyReader, path: Path, topic: str) -> Trajectory:
    tf_id = parse_tf_id(topic)
    _pick_topic(reader, path, tf_id.topic, (bm.TF_TYPE,), "TF transforms")
    buffer = TfBuffer()
    for name, static in ((tf_id.topic, False), (tf_id.static_topic, True)):
        conns = [c for c in reader.connections if c.topic == name and c.msgtype == bm.TF_TYPE]
        for conn, _, raw in _messages(reader, connections=conns) if conns else ():
            buffer.add(_deserialize(reader, raw, conn.msgtype), static)
    try:
        poses, stamps = buffer.trajectory(tf_id.parent, tf_id.child)
    except TfError as err:
        raise InputError(path, str(err), topic=topic) from None
    if len(poses) == 0:
        problem = f"no time at which {tf_id.child} in {tf_id.parent} can be looked up"
        raise InputError(path, problem, topic=topic)
    meta = {"frame_id": tf_id.parent, "child_frame_id": tf_id.child, "topic": topic}
    return _checked(path, topic, Trajectory(poses, stamps, meta=meta))


def read(path: Path, options: ReadOptions) -> Trajectory:
    """The trajectory on ``options.topic`` (or the bag's only pose topic)."""
    with open_bag(path) as reader:
        if options.topic is not None and parse_tf_id(options.topic) is not None:
            return _read_tf(reader, path, options.topic)
        topic = _pick_topic(reader, path, options.topic, bm.POSE_TYPES, "poses")
        stamps, xyz, quat, frame_id = [], [], [], None
        for conn, _, raw in _messages(reader, connections=reader.topics[topic].connections):
            msg = _deserialize(reader, raw, conn.msgtype)
            stamps.append(bm.stamp_seconds(msg.header.stamp))
            p, q = bm.pose_of(msg)
            xyz.append(p)
            quat.append(q)
            frame_id = msg.header.frame_id if frame_id is None else frame_id
    if not stamps:
        raise InputError(path, "no message could be read (the bag's index lists some)", topic=topic)
    quat = np.asarray(quat, dtype=np.float64)
    if (bad := bm.bad_quaternion(quat)).any():
        i = int(np.argmax(bad))
        problem = f"message {i} has quaternion {quat[i].tolist()} (not of unit norm)"
        raise InputError(path, problem, topic=topic)
    poses = se3.from_xyz_quat(np.asarray(xyz, dtype=np.float64), quat, "xyzw")
    return _checked(path, topic, Trajectory(poses, stamps, meta={"frame_id": frame_id, "topic": topic}))


def _write_messages(traj: Trajectory, writer, typestore, topic: str, ros1: bool) -> None:
    conn = writer.add_connection(topic, bm.WRITE_TYPE, typestore=typestore)
    xyz, quat = se3.to_xyz_quat(traj.poses, "xyzw")
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    for i, t in enumerate(traj.timestamps):
        sec, nsec = bm.seconds_to_sec_nsec(float(t))
        msg = bm.pose_stamped(typestore, sec, nsec, xyz[i], quat[i], "map", i)
        writer.write(conn, sec * 1_000_000_000 + nsec, serialize(msg, bm.WRITE_TYPE))


def _is_bag_folder(path: Path) -> bool:
    """A folder holding a ROS 2 bag and nothing else (metadata.yaml and its storage files): replaceable."""
    names = [p.name for p in path.iterdir()]
    return "metadata.yaml" in names and all(
        n == "metadata.yaml" or n.endswith((".db3", ".mcap", ".db3-shm", ".db3-wal")) for n in names)


def write(traj: Trajectory, path: Path, options: ReadOptions) -> None:
    """PoseStamped messages (frame "map", header stamps = trajectory stamps) on ``options.topic``:
    a ROS 1 ``.bag``, a bare ``.mcap`` or ``.db3`` file, or (any other name) a ROS 2 sqlite3 folder."""
    topic = options.topic or DEFAULT_WRITE_TOPIC
    if traj.timestamps is None:
        raise InputError(path, "writing a bag needs timestamps; this trajectory has none")
    if len(traj) and (not np.isfinite(traj.timestamps).all() or traj.timestamps.min() < 0):
        raise InputError(path, "bag stamps must be finite and not negative")
    suffix = path.suffix.lower()
    bare = suffix in SUFFIXES
    with atomic_path(path, folder=not bare, replaceable=_is_bag_folder) as tmp:
        if suffix == ".bag":
            with Writer1(tmp) as writer:
                _write_messages(traj, writer, get_typestore(Stores.ROS1_NOETIC), topic, ros1=True)
            return
        plugin = StoragePlugin.MCAP if suffix == ".mcap" else StoragePlugin.SQLITE3
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=f"{temp_prefix()}{path.name}-work-") as work:
            # rosbags names the storage file after the folder: write it as PATH's name, then move it
            folder = Path(work) / (path.stem if bare else path.name)
            with Writer2(folder, version=8, storage_plugin=plugin) as writer:
                _write_messages(traj, writer, get_typestore(Stores.ROS2_HUMBLE), topic, ros1=False)
            if bare:  # a bare storage file: take it out of the folder rosbags wrote
                (inner,) = folder.glob(f"*{suffix}")
                os.replace(inner, tmp)
            else:
                os.rename(folder, tmp)


class _LazyMessages:
    """Messages of one topic, fetched one at a time by (bag time, rank among equal bag times)."""

    def __init__(self, path: Path, topic: str, msgtype: str, keys: list[tuple[int, int]]) -> None:
        self.path, self.topic, self.msgtype, self.keys = path, topic, msgtype, keys
        self._stack: contextlib.ExitStack | None = None
        self._reader: AnyReader | None = None
        self._pid = -1

    def _open(self) -> AnyReader:
        if self._reader is None or self._pid != os.getpid():  # reopen in forked workers
            self._stack = contextlib.ExitStack()
            self._reader = self._stack.enter_context(open_bag(self.path))
            self._pid = os.getpid()
        return self._reader

    def __call__(self, i: int) -> Scan:
        reader = self._open()
        bag_ns, rank = self.keys[i]
        conns = reader.topics[self.topic].connections
        msgs = _messages(reader, connections=conns, start=bag_ns, stop=bag_ns + 1)
        for k, (conn, _, raw) in enumerate(msgs):
            if k == rank:
                try:
                    return bm.scan_of(_deserialize(reader, raw, conn.msgtype), self.msgtype)
                except ValueError as err:
                    raise InputError(self.path, f"message {i}: {err}", topic=self.topic) from None
        raise InputError(self.path, f"message {i} vanished from the bag", topic=self.topic)

    def __getstate__(self) -> dict:  # picklable for spawned data-loader workers
        return {**self.__dict__, "_stack": None, "_reader": None, "_pid": -1}

    def __del__(self) -> None:
        if self._stack is not None and self._pid == os.getpid():
            with contextlib.suppress(Exception):
                self._stack.close()


def open_scans(path: Path, options: ReadOptions) -> ScanSequence:
    """PointCloud2 or LaserScan messages of ``options.topic`` (or the bag's only scan topic)."""
    with open_bag(path) as reader:
        topic = _pick_topic(reader, path, options.topic, bm.SCAN_TYPES, "scans")
        msgtype = reader.topics[topic].msgtype
        keys, stamps = [], []
        for conn, bag_ns, raw in _messages(reader, connections=reader.topics[topic].connections):
            rank = keys[-1][1] + 1 if keys and keys[-1][0] == bag_ns else 0
            keys.append((bag_ns, rank))
            stamps.append(bm.stamp_seconds(_deserialize(reader, raw, conn.msgtype).header.stamp))
    stamps = np.asarray(stamps, dtype=np.float64)
    _checked(path, topic, Trajectory(se3.identity(len(stamps)), stamps))
    return ScanSequence(
        loader=_LazyMessages(path, topic, msgtype, keys), count=len(keys), timestamps=stamps,
        planar=msgtype == bm.LASERSCAN, source=f"{path} [topic {topic}]",
        meta={"topic": topic, "msgtype": msgtype},
    )


def describe(path: Path) -> list[tuple[str, str]]:
    """Storage kind, duration, message count and one row per topic."""
    with open_bag(path) as reader:
        topics = sorted(reader.topics.items())
        rows = [
            ("storage", _kind(path)),
            ("duration", f"{reader.duration * 1e-9:.3f} s" if 0 <= reader.duration < 2**63 else
             "unknown (the bag's metadata gives none that is a number of nanoseconds)"),
            ("messages", str(reader.message_count)),
        ]
        if topics:
            w_name = max(len(t) for t, _ in topics)
            w_type = max(len(i.msgtype or "mixed") for _, i in topics)
            rows += [
                ("topic", f"{t:<{w_name}}  {i.msgtype or 'mixed':<{w_type}}  {i.msgcount}") for t, i in topics
            ]
        rows += _tf_rows(reader)
    return rows


def _tf_rows(reader: AnyReader) -> list[tuple[str, str]]:
    """One row per TF frame pair ``parent -> child`` with its transform count and the ``--topic`` id that
    reads the pose of ``child`` in ``parent`` (any two connected frames can be named the same way)."""
    tf_topics = sorted(t for t, i in reader.topics.items() if i.msgtype == bm.TF_TYPE and i.msgcount > 0)
    if not tf_topics:
        return []
    dynamic = [t for t in tf_topics if "static" not in t]
    main = "/tf" if "/tf" in dynamic else (dynamic[0] if dynamic else None)
    counts: dict[tuple[str, str, str], int] = {}
    try:
        for topic in tf_topics:
            for conn, _, raw in _messages(reader, connections=reader.topics[topic].connections):
                for tf in _deserialize(reader, raw, conn.msgtype).transforms:
                    key = (topic, tf.header.frame_id, tf.child_frame_id)
                    counts[key] = counts.get(key, 0) + 1
    except (*_READ_ERRORS, KeyError) as exc:
        return [("tf", f"cannot read the TF messages ({exc})")]
    if not counts:
        return []
    pairs = [(f"{parent} -> {child}", topic, n, _tf_id(topic, parent, child, main)) for (topic, parent, child), n
             in sorted(counts.items(), key=lambda kv: (kv[0][0] not in dynamic, kv[0][1], kv[0][2]))]
    w_pair = max(len(p) for p, *_ in pairs)
    w_count = max(len(f"{n} on {t}") for _, t, n, _ in pairs)
    return [("tf", f"{pair:<{w_pair}}  {f'{n} on {topic}':<{w_count}}  " + (f"--topic {tf_id}" if tf_id else ""))
            for pair, topic, n, tf_id in pairs]


def _tf_id(topic: str, parent: str, child: str, main: str | None) -> str | None:
    """The ``/tf:PARENT.CHILD`` id of a pair seen on ``topic`` (a static topic is read with the dynamic one);
    None where no id can name it (no dynamic TF topic, or a frame name with a dot)."""
    if main is None or "." in parent:
        return None
    static = "" if topic == main or topic == "/tf_static" else f":{topic}"
    tf_id = f"{main}:{parent}.{child}{static}"
    return tf_id if parse_tf_id(tf_id) == TfId(main, parent, child, topic if static else "/tf_static") else None


def sniff(path: Path) -> bool:
    """A folder with metadata.yaml, or a file with a bag suffix."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in SUFFIXES


trajectory_format(TrajectoryFormat(
    name="bag", description="ROS 1/2 bag (.bag, .db3, .mcap, bag folder): pose topics or /tf:parent.child",
    read=read, write=write, suffixes=(*SUFFIXES, "/"), sniff=sniff, describe=describe,
))
scan_source(ScanSource(
    name="bag", description="ROS 1/2 bag: sensor_msgs/PointCloud2 or LaserScan topic",
    open=open_scans, suffixes=(*SUFFIXES, "/"), sniff=sniff, describe=describe,
))

