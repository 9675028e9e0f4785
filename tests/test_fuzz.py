"""Bad input never crashes dm2 (issue 17): a seconds-per-family fuzz budget over every reader, hypothesis
strategies for the text formats, and one regression test per failure kind found, each with a minimal
reproducer generated here (no stored binaries). The mutations and the oracle are ``tests/fuzzing.py``;
``benchmarks/fuzz.py`` runs the same with 10,000 inputs per family in a crash-proof subprocess."""

from __future__ import annotations

import bz2
import gzip
import io
import os
import pickle
import resource
import struct
import subprocess
import sys
from pathlib import Path

import fuzzing
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from shared_helpers import assert_one_line_error, run

from dm2_backend.formats import ReadOptions, open_scans, read_trajectory, write_trajectory
from dm2_backend.formats.scan_folder import read_scan_file
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_path, atomic_write, clean_stale
from dm2_backend.runtime.errors import InputError

SECONDS_PER_FAMILY = 1.2


# ------------------------------------------------------------------------------------------ budget


@pytest.mark.parametrize("family", sorted(fuzzing.FAMILIES))
def test_fuzz_budget(family, tmp_path):
    """Every mutated input ends as a clean read or a one-line error naming the file (deterministic inputs)."""
    fuzzing.seeds(family)  # built once, outside the time budget
    stats = fuzzing.run_family(family, seconds=SECONDS_PER_FAMILY, work=tmp_path)
    assert stats["inputs"] >= 5
    assert not stats["failures"], stats["examples"]


_NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64).map(repr),
    st.integers(min_value=-(10**30), max_value=10**30).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e308", "1e400", "-0", "0x1", "1_0", "", "abc", "\xff", "1e-400"]),
)
_LINE = st.lists(_NUMBER_TEXT, min_size=0, max_size=32).map(" ".join)
_TEXT = st.lists(st.one_of(_LINE, st.sampled_from(["# comment", "", ",,,", "VERTEX_SE2 0 0 0 0", "ODOM 1 2",
                                                   "FLASER 2 1 1 0 0 0 0 0 0 1.0 h 1.0"])),
                 min_size=0, max_size=12).map("\n".join)
_TEXT_FILES = {"tum": "traj.txt", "kitti": "poses.kitti", "euroc": "data.csv", "g2o": "graph.g2o",
               "carmen": "robot.log"}


@pytest.mark.parametrize("family", sorted(_TEXT_FILES))
@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(text=_TEXT, seed_lines=st.integers(0, 3))
def test_text_formats_hypothesis(family, text, seed_lines, tmp_path_factory):
    """Generated lines of numbers, NaN/inf, huge and broken tokens, after a few lines of a valid seed."""
    seed = fuzzing.seeds(family)[0]
    valid = seed.files[seed.entry].decode("latin-1").splitlines()[: seed_lines * 2]
    body = "\n".join(valid + [text]).encode("utf-8", "surrogateescape")
    name = _TEXT_FILES[family]
    outcome = fuzzing.check(family, {name: body}, name, None, tmp_path_factory.mktemp("hyp") / "case")
    assert outcome.ok, (outcome.kind, outcome.detail, body[:300])


# ------------------------------------------------------------------------- regression: tracebacks


def _info_fails_cleanly(path: Path) -> None:
    assert_one_line_error(run("info", str(path)), str(path))


def test_real_npz_scan_is_read_by_info(tmp_path):
    """The DM2-prior sniffing ran np.load on any unclaimed file: 'NpzFile' object has no attribute 'ndim'."""
    path = tmp_path / "scan.npz"
    np.savez_compressed(path, data=np.ones((5, 4), np.float32))
    result = run("info", str(path))
    assert result.exit_code == 0, result.output
    assert "points per scan" in result.output


def _npy(header: str, body: bytes = b"") -> bytes:
    head = header.encode("latin-1")
    head += b" " * ((-(10 + len(head) + 1)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(head)) + head + body


@pytest.mark.parametrize(("what", "data"), [
    ("malformed header", _npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3,")),
    ("13 TiB declared", _npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3000000000000, 1), }")),
    ("string field", _npy("{'descr': [('x', '<f4'), ('s', '<U3')], 'fortran_order': False, 'shape': (1,), }",
                          b"\0" * 16)),
    ("sub-array field", _npy("{'descr': [('x', '<f4', (2,))], 'fortran_order': False, 'shape': (1,), }",
                             b"\0" * 8)),
    ("objects", _npy("{'descr': '|O', 'fortran_order': False, 'shape': (1,), }", pickle.dumps([1]))),
    ("truncated body", _npy("{'descr': '<f4', 'fortran_order': False, 'shape': (4, 3), }", b"\0" * 8)),
    ("empty", b""),
])
def test_bad_npy_is_one_line(tmp_path, what, data):
    path = tmp_path / "000001.npy"
    path.write_bytes(data)
    _info_fails_cleanly(path)
    with pytest.raises(InputError):
        read_scan_file(path)


def test_bad_npz_is_one_line(tmp_path):
    good = io.BytesIO()
    np.savez_compressed(good, data=np.arange(300, dtype=np.float32).reshape(100, 3))
    raw = bytearray(good.getvalue())
    cases = {"not_zip.npz": b"PK\x03\x04 not a zip", "empty.npz": b""}
    # a corrupt deflate stream: flip bytes inside the member's compressed data
    corrupt = raw.copy()
    for k in range(60, 90):
        corrupt[k] ^= 0x5A
    cases["deflate.npz"] = bytes(corrupt)
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        _info_fails_cleanly(path)


def test_corrupt_compressed_carmen_is_one_line(tmp_path):
    log = b"ODOM 0 0 0 0 0 0 1.0 h 0.0\n" * 50
    for name, data in (("a.log.gz", gzip.compress(log)), ("b.clf.bz2", bz2.compress(log))):
        bad = bytearray(data)
        for k in range(15, 30):
            bad[k] ^= 0xFF
        path = tmp_path / name
        path.write_bytes(bytes(bad))
        _info_fails_cleanly(path)


def test_g2o_overflows_are_one_line(tmp_path):
    big_id = tmp_path / "id.g2o"
    big_id.write_text("VERTEX_SE2 99999999999999999999999 0 0 0\n")
    _info_fails_cleanly(big_id)
    big_info = tmp_path / "info.g2o"
    big_info.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1e308 0 0 1e308 0 1e308\n")
    _info_fails_cleanly(big_info)


def test_euroc_stamp_beyond_float_range(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("#t,x,y,z,qw,qx,qy,qz\n" + "9" * 400 + ",0,0,0,1,0,0,0\n")
    _info_fails_cleanly(path)


def test_pcd_counts_are_checked(tmp_path):
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT {}\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary\n"
    for name, counts in (("zero.pcd", "0 1 1"), ("huge.pcd", "1 1 4000000000")):
        path = tmp_path / name
        path.write_bytes(head.format(counts).encode() + b"\0" * 12)
        _info_fails_cleanly(path)
    comp = tmp_path / "comp.pcd"
    comp.write_bytes(head.format("1 1 1").replace("binary", "binary_compressed").encode()
                     + struct.pack("<II", 4, 4_000_000_000) + b"\0\0\0\0")
    _info_fails_cleanly(comp)


def test_depth_png_bomb_and_broken_chunk(tmp_path):
    folder = tmp_path / "seq"
    folder.mkdir()
    png = fuzzing.png_bytes(np.full((4, 4), 1000, np.uint16))
    chunks = fuzzing._png_chunks(png)
    chunks[0][1] = struct.pack(">II", 1_000_000, 1_000_000) + chunks[0][1][8:]  # 10^12 pixels declared
    (folder / "frame-000000.depth.png").write_bytes(fuzzing._png_join(chunks))
    assert_one_line_error(run("info", str(folder)), str(folder))
    chunks = fuzzing._png_chunks(png)
    huge = fuzzing._png_join(chunks)
    at = huge.find(b"IDAT") - 4
    huge = huge[:at] + struct.pack(">I", 0xFFFFFF00) + huge[at + 4:]  # a chunk length of 4 GiB: PIL read it at once
    (folder / "frame-000000.depth.png").write_bytes(huge)
    assert_one_line_error(run("info", str(folder)), str(folder))
    broken = bytearray(png)
    broken[40] ^= 0xFF  # inside IDAT, CRC now wrong
    (folder / "frame-000000.depth.png").write_bytes(bytes(broken))
    assert_one_line_error(run("info", str(folder)), str(folder))


def test_empty_scan_files_are_one_line(tmp_path):
    """An empty .bin/.ply/.pcd/.npy/.npz printed only 'Aborted!'."""
    for suffix in (".bin", ".ply", ".pcd", ".npy", ".npz"):
        path = tmp_path / f"empty{suffix}"
        path.write_bytes(b"")
        _info_fails_cleanly(path)


# --- PLY: parsed in numpy, never by open3d's C++ reader


def test_ply_reads_ascii_binary_and_open3d_output(tmp_path):
    pts = fuzzing._cloud()
    for fmt in ("ascii", "binary_little_endian", "binary_big_endian"):
        path = tmp_path / f"{fmt}.ply"
        path.write_bytes(fuzzing.ply_bytes(pts, fmt, faces=True))
        scan = read_scan_file(path)
        np.testing.assert_array_equal(scan.points, pts)
        assert scan.intensity is not None and len(scan.intensity) == len(pts)
    import open3d as o3d  # dm2 writes map.ply with open3d: dm2 must read it back

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    o3d.io.write_point_cloud(str(tmp_path / "o3d.ply"), cloud)
    np.testing.assert_allclose(read_scan_file(tmp_path / "o3d.ply").points, pts)


@pytest.mark.parametrize("what", ["truncated binary", "truncated ascii", "long token", "non-utf8 name",
                                  "huge count", "no vertex"])
def test_hostile_ply_is_one_line(tmp_path, what):
    """open3d's reader aborted the interpreter on a long header token and segfaulted on truncated data."""
    data = fuzzing.ply_bytes(fuzzing._cloud(), "ascii" if "ascii" in what else "binary_little_endian")
    data = {
        "truncated binary": data[:-30], "truncated ascii": data[:-60],
        "long token": data.replace(b"property float x", b"property float x" + b"A" * 70000),
        "non-utf8 name": data.replace(b"property float y", b"property float \xff\xfe"),
        "huge count": data.replace(b"element vertex 16", b"element vertex 99999999999999"),
        "no vertex": data.replace(b"element vertex", b"element points"),
    }[what]
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    _info_fails_cleanly(path)


# --- bags


def test_ros2_bag_corruption_is_one_line(tmp_path):
    src = tmp_path / "src"
    write_trajectory(_traj(), src, "bag")
    cases = {
        "yaml_bytes": lambda d: (d / "metadata.yaml").write_bytes(b"\xff\xfe" + (d / "metadata.yaml").read_bytes()),
        "yaml_types": lambda d: (d / "metadata.yaml").write_text(
            (d / "metadata.yaml").read_text().replace("message_count: 5", "message_count: five")),
        "sqlite": lambda d: (d / f"{d.name}.db3").write_bytes(b"SQLite format 3\0" + b"\xff" * 2000),
    }
    for name, damage in cases.items():
        folder = tmp_path / name
        folder.mkdir()
        for f in src.iterdir():
            target = f.name.replace("src", name)
            (folder / target).write_bytes(f.read_bytes().replace(b"src.db3", f"{name}.db3".encode()))
        damage(folder)
        result = run("info", str(folder), "--topic", "/dm2/poses")
        assert_one_line_error(result, str(folder))


def test_unknown_message_type_is_a_read_error(tmp_path):
    """MCAP whose schema names a type the typestore lacks: KeyError from rosbags' deserialiser (reproducer:
    ``fuzzing.make_input("mcap", 554)``, a flipped byte in a schema name)."""
    from rosbags.serde import SerdeError
    from rosbags.typesys import Stores, get_typestore

    from dm2_backend.formats.bag import _deserialize

    class Fake:
        typestore = get_typestore(Stores.ROS2_HUMBLE)

        def deserialize(self, raw, msgtype):
            raise KeyError("built/n_interfaces/msg/Time")

    with pytest.raises(SerdeError, match="KeyError"):
        _deserialize(Fake(), b"", "geometry_msgs/msg/PoseStamped")

    class Corrupt(Fake):  # the bag's own schema lost the header field: objects without .header
        typestore = type("Store", (), {"fielddefs": {
            **Fake.typestore.fielddefs,
            "geometry_msgs/msg/PoseStamped": ([], Fake.typestore.fielddefs["geometry_msgs/msg/PoseStamped"][1][1:]),
        }})()

    with pytest.raises(SerdeError, match="not the standard one"):
        _deserialize(Corrupt(), b"", "geometry_msgs/msg/PoseStamped")
    files, entry, topic = fuzzing.make_input("mcap", 554)
    assert fuzzing.check("mcap", files, entry, topic, tmp_path / "case").ok


def test_bag_chunk_decompression_is_bounded_and_checked():
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag1 import reader as reader1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.rosbag2 import storage_mcap

    from dm2_backend.formats import bag

    with pytest.raises(ReaderError2):
        storage_mcap.DECOMPRESSORS["zstd"](b"not zstd", 10)
    with pytest.raises(ReaderError2):
        storage_mcap.DECOMPRESSORS["lz4"](b"x", bag.MAX_CHUNK_BYTES + 1)
    with pytest.raises(ReaderError1):
        reader1.decompressors["lz4"](b"\x04\x22\x4d\x18 corrupt lz4 frame")
    import lz4.frame

    bomb = lz4.frame.compress(b"\0" * 4096)
    assert bag._bounded("lz4", bomb, 4096, ReaderError1) == b"\0" * 4096
    with pytest.raises(ReaderError1):
        bag._bounded("lz4", bomb, 1024, ReaderError1)


def test_rosbags_assertion_becomes_a_read_error():
    """rosbags checks a ROS 1 bag's index with assert (and fails with KeyError on unknown connections)."""
    from rosbags.rosbag1 import ReaderError as ReaderError1

    from dm2_backend.formats.bag import _messages

    class Fake:
        def messages(self, **_):
            yield 1
            raise AssertionError

    with pytest.raises(ReaderError1):
        list(_messages(Fake()))


def _traj(n: int = 5, stamps=None) -> Trajectory:
    return Trajectory(se3.identity(n), np.arange(n, dtype=float) + 10.0 if stamps is None else stamps)


# ------------------------------------------------------------------ regression: garbage accepted


def test_carmen_nan_pose_is_refused_at_read(tmp_path):
    path = tmp_path / "r.log"
    path.write_text("ODOM 0 0 0 0 0 0 1.0 h 0\nODOM nan 0 0 0 0 0 2.0 h 1\n")
    assert_one_line_error(run("convert", str(path), str(tmp_path / "o.txt"), "--to", "tum"), str(path))
    huge = tmp_path / "h.log"
    huge.write_text("ODOM 0 0 0 0 0 0 1.0 h 0\nODOM 1e308 0 0 0 0 0 2.0 h 1\n")
    assert_one_line_error(run("convert", str(huge), str(tmp_path / "o.txt"), "--to", "tum"), str(huge))
    assert not (tmp_path / "o.txt").exists()


def test_carmen_stamps_never_reach_a_writer_that_cannot_read_them(tmp_path):
    """Unsorted CARMEN stamps were converted to a TUM file dm2 then refused; repeated ones read back."""
    unsorted = tmp_path / "u.log"
    unsorted.write_text("ODOM 0 0 0 0 0 0 2.0 h 0\nODOM 1 0 0 0 0 0 1.0 h 1\n")
    assert_one_line_error(run("convert", str(unsorted), str(tmp_path / "u.txt"), "--to", "tum"), str(unsorted))
    assert not (tmp_path / "u.txt").exists()
    repeated = tmp_path / "r.log"
    repeated.write_text("ODOM 0 0 0 0 0 0 1.0 h 0\nODOM 1 0 0 0 0 0 1.0 h 1\nODOM 2 0 0 0 0 0 2.0 h 1\n")
    out = tmp_path / "r.txt"
    result = run("convert", str(repeated), str(out), "--to", "tum")
    if result.exit_code == 0:
        assert len(read_trajectory(out)) == 3  # what dm2 writes, dm2 reads
    else:
        assert_one_line_error(result, str(repeated))
    first = read_trajectory(repeated, options=ReadOptions(duplicate_times="keep-first"))
    assert len(first) == 2
    with pytest.raises(InputError, match="cannot write bag"):
        write_trajectory(read_trajectory(unsorted), tmp_path / "k.txt", "bag")


def test_multi_line_messages_are_collapsed(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(b"seed: 1\nframes:\n  voxel: \x00\n")
    from dm2_backend import config

    with pytest.raises(InputError) as err:
        config.load(cfg)
    assert "\n" not in err.value.message and str(cfg) in err.value.message
    assert InputError("f", "a\n  b\r\nc").message == "f: a b c"


def test_non_utf8_config_is_one_line(tmp_path):
    from dm2_backend import config

    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(b"seed: \xff\xfe\n")
    with pytest.raises(InputError, match="not UTF-8"):
        config.load(cfg)


# ---------------------------------------------------------------------- nothing of the user's is lost


def test_convert_into_an_existing_folder_keeps_it(tmp_path):
    """`dm2 convert traj.txt EXISTING_DIR --to bag` deleted everything in EXISTING_DIR."""
    src = tmp_path / "t.txt"
    write_trajectory(_traj(), src, "tum")
    keep = tmp_path / "mine"
    keep.mkdir()
    (keep / "precious.txt").write_text("do not lose me")
    for fmt in ("bag", "tum"):
        result = run("convert", str(src), str(keep), "--to", fmt)
        assert_one_line_error(result, str(keep))
        assert (keep / "precious.txt").read_text() == "do not lose me"
        assert sorted(p.name for p in keep.iterdir()) == ["precious.txt"]
    assert not list(tmp_path.glob(".tmp-*"))


def test_bag_folder_has_no_hidden_temporary_storage(tmp_path):
    out = tmp_path / "newbag"
    write_trajectory(_traj(), out, "bag")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["metadata.yaml", "newbag.db3"], names
    assert "newbag.db3" in (out / "metadata.yaml").read_text()
    assert len(read_trajectory(out)) == 5
    assert not list(tmp_path.glob(".tmp-*"))


def test_output_parent_is_a_file(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="parent is a file"):
        with atomic_write(tmp_path / "file" / "out.txt") as fh:
            fh.write("y")
    with pytest.raises(InputError, match="existing folder"):
        with atomic_path(tmp_path) as tmp:
            tmp.mkdir()


def test_stale_temporaries_of_dead_processes_are_cleaned(tmp_path):
    """A writer removes the temporaries a dead writer of the same output left (its file, a bag's work folder),
    never another name's: a folder of the user's named like a temporary (``.tmp-999999-photos``) stays."""
    dead = 2**22 + 12345  # above the default pid_max: no such process
    (tmp_path / f".tmp-{dead}-out.txt").write_text("half")
    (tmp_path / f".tmp-{dead}-out.txt-work-x").mkdir()
    (tmp_path / f".tmp-{dead}-photos").mkdir()
    (tmp_path / f".tmp-{dead}-photos" / "a.jpg").write_text("mine")
    mine = tmp_path / f".tmp-{os.getpid()}-busy.txt"
    mine.write_text("being written")
    (tmp_path / "user.tmp-1-file").write_text("not ours")
    with atomic_write(tmp_path / "out.txt") as fh:
        fh.write("ok")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([mine.name, "user.tmp-1-file", "out.txt",
                                                                f".tmp-{dead}-photos"])
    assert (tmp_path / f".tmp-{dead}-photos" / "a.jpg").read_text() == "mine"
    assert clean_stale(tmp_path, ("out.txt",)) == []


def test_failed_writer_leaves_no_temporary(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "x.bag") as tmp:
            tmp.write_text("partial")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------- safe loading


class _Payload:
    def __reduce__(self):
        return (os.system, ("touch PWNED_BY_CHECKPOINT",))


def test_checkpoint_loads_without_running_code(tmp_path, monkeypatch):
    from dm2_backend.optim.checkpoint import load_checkpoint, plain_state
    from dm2_backend.optim.epoch import Epoch, TracePoint
    from dm2_backend.optim.selection import Best

    monkeypatch.chdir(tmp_path)
    evil = tmp_path / "checkpoint.pt"
    torch.save({"best": {"poses": _Payload()}}, evil)
    with pytest.raises(InputError, match="checkpoint"):
        load_checkpoint(evil, "cpu")
    assert not (tmp_path / "PWNED_BY_CHECKPOINT").exists()
    good = tmp_path / "good.pt"
    row = Epoch(0, 0.5, 1.0, 3, (TracePoint(3, 0.5, 0.1),), chamfer=0.2, map_entropy=-4.0).row()
    state = plain_state({"best": Best(np.eye(4)[None], 0, np.float64(0.5)).state(), "history": [row], "epoch": 0})
    torch.save(state, good)
    back = load_checkpoint(good, "cpu")
    assert isinstance(back["best"].poses, np.ndarray) and back["best"].loss == 0.5 and back["best"].epoch == 0
    assert back["history"] == [Epoch.of_row(row)] and back["history"][0].trace[0].ate == 0.1
    for damaged in ({**row, "loss": "low"}, {**row, "trace": [{"step": -1, "loss": 0.5}]}, {**row, "rejected": 3}):
        torch.save(plain_state({**state, "history": [damaged]}), good)
        with pytest.raises(InputError, match="not a checkpoint of this run"):
            load_checkpoint(good, "cpu")


def test_pickled_npy_is_never_unpickled(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "prior" / "init_pose.npy"
    path.parent.mkdir()
    np.save(path, np.array([_Payload()], dtype=object), allow_pickle=True)
    _info_fails_cleanly(path)
    assert_one_line_error(run("info", str(path), "--format", "dm2"), str(path))
    assert not (tmp_path / "PWNED_BY_CHECKPOINT").exists()


def test_config_yaml_is_safe_loaded(tmp_path, monkeypatch):
    from dm2_backend import config

    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("seed: !!python/object/apply:os.system ['touch PWNED_BY_CHECKPOINT']\n")
    with pytest.raises(InputError):
        config.load(cfg)
    assert not (tmp_path / "PWNED_BY_CHECKPOINT").exists()


def test_output_names_from_content_are_sanitised():
    from dm2_backend.evaluation.report_writers import safe_name

    for label in ("/tf:map.base/../../etc/passwd", "../../x", "a/b\\c", "\0\n", "topic with spaces"):
        name = safe_name(label)
        assert name and "/" not in name and "\\" not in name and not name.startswith(".") and "\0" not in name


def test_scan_bag_with_no_messages_is_one_line(tmp_path):
    """A topic whose messages cannot be read ended in min() of an empty sequence."""
    path = tmp_path / "s.bag"
    fuzzing._write_scan_bag(path, ros1=True)
    seq = open_scans(path, None, ReadOptions(topic="/points"))
    assert len(seq) == 3
    data = bytearray(path.read_bytes())
    pos = data.find(b"/points", 200)
    for k in range(pos + 200, min(pos + 400, len(data))):
        data[k] ^= 0xA5
    path.write_bytes(bytes(data))
    result = run("info", str(path), "--topic", "/points")
    assert result.exit_code in (0, 2), result.output
    if result.exit_code == 2:
        assert_one_line_error(result, str(path))



def test_absurd_numbers_are_refused_not_printed_as_inf(tmp_path):
    """Finite but absurd values overflowed later: a 1e308 position (path length inf m), a chained g2o edge,
    a ROBOTLASER1 angular resolution of 1e308 (beam angles up to +inf deg)."""
    g2o = tmp_path / "far.g2o"
    g2o.write_text("EDGE_SE2 0 1 1e308 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1e308 0 0 1 0 0 1 0 1\n")
    _info_fails_cleanly(g2o)
    tum = tmp_path / "far.txt"
    tum.write_text("1 0 0 0 0 0 0 1\n2 1e308 0 0 0 0 0 1\n3 -1e308 0 0 0 0 0 1\n")
    _info_fails_cleanly(tum)
    log = tmp_path / "angles.log"
    log.write_text("ROBOTLASER1 0 -1.5708 3.1416 1e308 20.0 0.1 0 2 1.0 2.0 0 0 0 0 0 0 0 0 0 0 0 0 1.0 h 0.1\n")
    _info_fails_cleanly(log)


# ------------------------------------------------ hostile files: FIFOs, devices, symlink loops, YAML aliases
#: a real dm2 process under a memory cap (a read without a bound fails fast instead of eating the machine) and a
#: timeout (a read that blocks fails the test instead of hanging the suite)
MEMORY_CAP = 3 << 30


def _capped_dm2(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "dm2_backend", *args], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=cap, env=env)


def _one_capped_line(done: subprocess.CompletedProcess, *words: str) -> None:
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dm2: error:"), done.stderr[-2000:]
    for word in words:
        assert word in lines[0], lines[0]


@pytest.fixture(scope="module")
def small_scans(tmp_path_factory) -> Path:
    from dm2_backend.simulate.sequence import write_sequence

    rng = np.random.default_rng(0)
    poses = se3.identity(4)
    poses[:, 0, 3] = np.arange(4) * 0.1
    scans = [rng.normal(size=(64, 3)).astype(np.float32) for _ in range(4)]
    root = tmp_path_factory.mktemp("hostile")
    write_sequence(root, scans, poses, poses, 10.0)
    return root


def _refine(root: Path, out: Path, *extra: str) -> list[str]:
    return ["refine", "--scans", str(root / "velodyne"), "--out", str(out), "-q", "--no-cache", *extra]


@pytest.mark.parametrize("option", ["--poses", "--config"])
def test_dev_zero_is_refused_not_read(small_scans, tmp_path, option):
    """`-p /dev/zero --poses-format tum` and `--config /dev/zero` grew to 22 GB before the kernel killed them."""
    extra = [option, "/dev/zero", *(["--poses-format", "tum"] if option == "--poses" else [])]
    _one_capped_line(_capped_dm2(*_refine(small_scans, tmp_path / "run", *extra)), "/dev/zero", "character device")
    assert not (tmp_path / "run").exists()


def test_a_fifo_is_refused_not_waited_on(small_scans, tmp_path):
    """`--times FIFO` blocked forever in open(); `dm2 info FIFO` too."""
    fifo = tmp_path / "times.txt"
    os.mkfifo(fifo)
    _one_capped_line(_capped_dm2(*_refine(small_scans, tmp_path / "run", "--poses",
                                          str(small_scans / "warm_start.txt"), "--times", str(fifo))), "FIFO")
    _one_capped_line(_capped_dm2("info", str(fifo)), "FIFO")


def test_a_yaml_alias_bomb_is_refused(small_scans, tmp_path):
    """Nested anchors under `seed:` expand to 9**9 values: building the error message never ended."""
    levels = "abcdefghi"
    rows = ["seed:", "  - &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    rows += [f"  - &{b} [{', '.join([f'*{a}'] * 9)}]" for a, b in zip(levels, levels[1:], strict=False)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(rows) + "\n")
    _one_capped_line(_capped_dm2(*_refine(small_scans, tmp_path / "run", "--poses",
                                          str(small_scans / "warm_start.txt"), "-c", str(bomb))),
                     str(bomb), "aliases")


def test_an_oversized_config_is_refused_by_its_size(tmp_path):
    from dm2_backend import config

    big = tmp_path / "big.yaml"
    with open(big, "wb") as fh:
        fh.truncate(64 << 20)  # sparse: no disk used
    with pytest.raises(InputError, match="larger than"):
        config.load(big)


def test_symlink_loops_are_one_line(small_scans, tmp_path):
    """A symlink loop as the scan folder, as a scan and as the trajectory: ELOOP tracebacks in info/refine."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    _one_capped_line(_capped_dm2("info", str(loop)), str(loop), "symbolic links")
    _one_capped_line(_capped_dm2(*_refine(small_scans, tmp_path / "run", "--poses", str(loop))), str(loop))
    _one_capped_line(_capped_dm2("refine", "--scans", str(loop), "--out", str(tmp_path / "run"), "-q"), str(loop))
