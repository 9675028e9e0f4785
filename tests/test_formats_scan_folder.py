"""Scan folders (KITTI .bin, PCD, PLY, npy/npz) and the PCD codec, on real files and round trips."""

from __future__ import annotations

import os
import string
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from shared_helpers import DATA, need

from dm2_backend.cli.main import cli
from dm2_backend.formats import ReadOptions, detect_scan_source, open_scans
from dm2_backend.formats import pcd as pcdmod
from dm2_backend.formats.scan_folder import (
    natural_key,
    read_scan_file,
    scan_files,
    stamps_from_names,
    write_bin,
    write_pcd,
)
from dm2_backend.runtime.errors import InputError

LIDAR = DATA / "lidar3d"


def o3d_points(path: Path) -> np.ndarray:
    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


def xyz(fields: dict) -> np.ndarray:
    return np.stack([fields["x"], fields["y"], fields["z"]], 1)


# ---------------------------------------------------------------- real files


def test_kitti_bin_folder_real():
    folder = need(LIDAR / "kitti00")
    seq = open_scans(folder)
    assert seq.meta["format"] == "folder" and len(seq) == 6
    np.testing.assert_array_equal(seq.timestamps, np.loadtxt(folder / "times.txt"))
    for i in (0, 5):
        raw = np.fromfile(folder / f"{i:06d}.bin", dtype=np.float32).reshape(-1, 4)
        scan = seq[i]
        np.testing.assert_array_equal(scan.points, raw[:, :3])
        np.testing.assert_array_equal(scan.intensity, raw[:, 3])
        assert scan.timestamp == seq.timestamps[i]


def test_kitti_velodyne_subfolder_and_parent_times(tmp_path):
    src = need(LIDAR / "kitti00")
    (tmp_path / "velodyne").mkdir()
    for f in sorted(src.glob("*.bin")):
        os.symlink(f, tmp_path / "velodyne" / f.name)
    (tmp_path / "times.txt").write_text((src / "times.txt").read_text())
    seq = open_scans(tmp_path)
    assert len(seq) == 6 and seq.meta["times_from"] == str(tmp_path / "times.txt")
    direct = open_scans(tmp_path / "velodyne")  # parent's times.txt found too
    np.testing.assert_array_equal(direct.timestamps, seq.timestamps)
    assert len(direct[3]) == (src / "000003.bin").stat().st_size // 16


def test_dgp_npz_folder_real():
    folder = need(LIDAR / "dgp_scene_02" / "point_cloud" / "LIDAR")
    seq = open_scans(folder)
    assert len(seq) == 3 and seq.meta["times_from"] == "file names"
    np.testing.assert_allclose(seq.timestamps[0], 1561645825.00279, atol=1e-6)
    assert np.allclose(np.diff(seq.timestamps), 0.1, atol=0.005)
    files = scan_files(folder)
    data = np.load(files[1])["data"]
    scan = seq[1]
    np.testing.assert_allclose(scan.points, data[:, :3].astype(np.float32))
    np.testing.assert_allclose(scan.intensity, data[:, 3].astype(np.float32))


REAL_PCDS = ["koide3_pair/251370668.pcd", "koide3_pair/251371071.pcd", "nebula/vlp16.pcd",
             "nebula/hesai_xt32.pcd", "nebula/ascii_xyz.pcd", "nebula/binary_xyz_pcl.pcd"]


@pytest.mark.parametrize("name", REAL_PCDS)
def test_pcd_agrees_with_open3d(name):
    path = need(LIDAR / name)
    scan = read_scan_file(path)
    np.testing.assert_array_equal(scan.points.astype(np.float64), o3d_points(path))
    header, fields = pcdmod.read_pcd(path)
    tensor = o3d.t.io.read_point_cloud(str(path))
    for key in set(fields) - set("xyz"):
        np.testing.assert_array_equal(fields[key], tensor.point[key].numpy()[:, 0])


def test_pcd_field_mapping_vlp16():
    path = need(LIDAR / "nebula" / "vlp16.pcd")
    header, fields = pcdmod.read_pcd(path)
    assert header.fields[3:] == ["intensity", "return_type", "channel", "azimuth", "elevation", "distance",
                                 "time_stamp"]
    assert fields["intensity"].dtype == np.uint8 and fields["channel"].dtype == np.uint16
    scan = read_scan_file(path)
    assert len(scan) == header.points == 14831
    np.testing.assert_array_equal(scan.intensity, fields["intensity"].astype(np.float32))
    np.testing.assert_array_equal(scan.ring, fields["channel"])
    np.testing.assert_allclose(scan.point_time, fields["time_stamp"] * 1e-9)  # uint32 ns -> s
    assert set(np.unique(scan.ring)) <= set(range(16))


def test_koide3_pair_folder_has_no_times():
    seq = open_scans(need(LIDAR / "koide3_pair"))
    assert len(seq) == 2 and seq.timestamps is None  # 9-digit names are frame numbers
    assert seq[0].intensity is not None


def test_cli_info_folder():
    folder = need(LIDAR / "kitti00")
    result = CliRunner().invoke(cli, ["info", str(folder)])
    assert result.exit_code == 0, result.output
    assert "folder" in result.output and "scans" in result.output and "6 x .bin" in result.output


# ---------------------------------------------------------------- PCD round trips


def _cloud(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)).astype(np.float32) * 10
    fields = {
        "intensity": rng.random(n).astype(np.float32),
        "ring": rng.integers(0, 64, n).astype(np.uint16),
        "t": rng.integers(0, 2**31, n).astype(np.uint32),
        "d": rng.normal(size=n),  # float64
        "signed": rng.integers(-100, 100, n).astype(np.int8),
        "normal": rng.normal(size=(n, 3)).astype(np.float32),  # COUNT 3
        "big": rng.integers(-(2**62), 2**62, n, dtype=np.int64),
    }
    return pts, fields


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip_and_open3d_reads_ours(tmp_path, mode):
    pts, fields = _cloud(500)
    path = tmp_path / f"c_{mode}.pcd"
    write_pcd(path, pts, fields, binary=mode != "ascii", compressed=mode == "binary_compressed")
    header, back = pcdmod.read_pcd(path)
    assert header.data == mode and header.counts[header.fields.index("normal")] == 3
    np.testing.assert_array_equal(xyz(back), pts)
    for k, v in fields.items():
        assert back[k].dtype == v.dtype
        np.testing.assert_array_equal(back[k], v)
    np.testing.assert_allclose(o3d_points(path), pts, rtol=1e-6, atol=1e-6)
    scan = read_scan_file(path)
    np.testing.assert_allclose(scan.point_time, fields["t"] * 1e-9)
    np.testing.assert_array_equal(scan.ring, fields["ring"])


def test_pcd_reads_open3d_compressed(tmp_path):
    pts, _ = _cloud(3000, seed=1)
    pts[::7] = pts[0]  # repeats give LZF back references
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    path = tmp_path / "o3d.pcd"
    o3d.io.write_point_cloud(str(path), cloud, compressed=True)
    header, fields = pcdmod.read_pcd(path)
    assert header.data == "binary_compressed"
    np.testing.assert_array_equal(xyz(fields), pts)


def test_pcd_organised_nan_dropped(tmp_path):
    pts = np.arange(24, dtype=np.float32).reshape(8, 3)
    pts[[1, 6]] = np.nan
    path = tmp_path / "org.pcd"
    write_pcd(path, pts, width=4, height=2, intensity=np.arange(8, dtype=np.float32))
    header, _ = pcdmod.read_pcd(path)
    assert (header.width, header.height, header.points) == (4, 2, 8)
    scan = read_scan_file(path)
    np.testing.assert_array_equal(scan.points, pts[[0, 2, 3, 4, 5, 7]])
    np.testing.assert_array_equal(scan.intensity, [0, 2, 3, 4, 5, 7])
    kept = o3d.io.read_point_cloud(str(path), remove_nan_points=True).points
    np.testing.assert_array_equal(np.asarray(kept), scan.points)


def test_lzf_corrupt_raises():
    packed = pcdmod.lzf_compress(b"abcabcabcabcabcabc" * 10)
    assert pcdmod.lzf_decompress(packed, 180) == b"abcabcabcabcabcabc" * 10
    with pytest.raises(ValueError):
        pcdmod.lzf_decompress(packed, 181)
    with pytest.raises(ValueError):
        pcdmod.lzf_decompress(bytes([0x20, 0x05]), 3)  # back reference before the start


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([b"", b"a", b"ab", b"\x00\x00\x00\x00", b"xyz1", bytes(range(7))]),
                max_size=60),
       st.binary(max_size=300))
def test_lzf_round_trip(chunks, noise):
    data = b"".join(chunks) + noise + b"".join(reversed(chunks))
    assert pcdmod.lzf_decompress(pcdmod.lzf_compress(data), len(data)) == data


# ---------------------------------------------------------------- PCD header / ascii property tests

_TYPES = [("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)]
_names = st.text(string.ascii_lowercase + "_", min_size=2, max_size=8).filter(lambda s: s not in "xyz")


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(_names, st.sampled_from(_TYPES), st.integers(1, 4)), max_size=5,
                unique_by=lambda f: f[0]),
       st.integers(0, 50), st.sampled_from([" ", "\t", "  "]), st.booleans(), st.booleans())
def test_header_parser_property(fields, width, sep, lower, comments):
    names = ["x", "y", "z"] + [f[0] for f in fields]
    types = ["F"] * 3 + [f[1][0] for f in fields]
    sizes = [4] * 3 + [f[1][1] for f in fields]
    counts = [1] * 3 + [f[2] for f in fields]
    lines = [
        "# .PCD v0.7", "VERSION 0.7", "FIELDS " + sep.join(names), "SIZE " + sep.join(map(str, sizes)),
        "TYPE " + sep.join(types), "COUNT " + sep.join(map(str, counts)), f"WIDTH{sep}{width}", "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {width}", "DATA binary",
    ]
    if lower:
        lines = [ln.split(" ", 1)[0].lower() + ln[len(ln.split(" ", 1)[0]):] for ln in lines]
    if comments:
        lines.insert(3, "# a comment")
        lines.insert(1, "")
    h = pcdmod.parse_header([ln + "\n" for ln in lines])
    assert (h.fields, h.types, h.sizes, h.counts, h.width, h.points, h.data) == (
        names, types, sizes, counts, width, width, "binary")
    assert h.data_line == len(lines)
    again = pcdmod.parse_header(h.text().splitlines(keepends=True))
    assert (again.fields, again.types, again.sizes, again.counts) == (names, types, sizes, counts)


@pytest.mark.parametrize("bad, line", [
    ("FIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n", 2),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nWIDTH 1\nDATA ascii\n", 3),
    ("FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nWIDTH 1\nDATA ascii\n", 3),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH one\nDATA ascii\n", 4),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 3\nDATA ascii\n", 6),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA zip\n", 5),
    ("FIELDS x y x\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n", 1),
])
def test_header_errors_name_the_line(bad, line):
    with pytest.raises(InputError) as exc:
        pcdmod.parse_header(bad.splitlines(keepends=True), "f.pcd")
    assert exc.value.line == line and exc.value.source == "f.pcd"


def test_header_without_data_line():
    with pytest.raises(InputError, match="no DATA line"):
        pcdmod.parse_header(["FIELDS x y z\n", "WIDTH 1\n"], "f.pcd")


_finite32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(_finite32, _finite32, _finite32, st.integers(0, 255),
                          st.integers(-(2**31), 2**31 - 1)), min_size=1, max_size=30))
def test_ascii_pcd_property(tmp_path, rows):
    pts = np.array([r[:3] for r in rows], dtype=np.float32)
    u8 = np.array([r[3] for r in rows], dtype=np.uint8)
    i32 = np.array([r[4] for r in rows], dtype=np.int32)
    path = tmp_path / "a.pcd"
    write_pcd(path, pts, {"label": u8, "ring": i32}, binary=False)
    _, back = pcdmod.read_pcd(path)
    np.testing.assert_array_equal(xyz(back), pts)
    np.testing.assert_array_equal(back["label"], u8)
    np.testing.assert_array_equal(back["ring"], i32)


def test_ascii_pcd_bad_value_names_line(tmp_path):
    path = tmp_path / "bad.pcd"
    header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nPOINTS 3\nDATA ascii\n"
    path.write_text(header + "1 2 3\n4 5 six\n7 8 9\n")
    with pytest.raises(InputError) as exc:
        pcdmod.read_pcd(path)
    assert exc.value.line == 9 and "six" in exc.value.problem
    path.write_text(header + "1 2 3\n4 5\n7 8 9\n")
    with pytest.raises(InputError) as exc:
        pcdmod.read_pcd(path)
    assert exc.value.line == 9 and "3 values" in exc.value.problem
    path.write_text(header + "1 2 3\n")
    with pytest.raises(InputError, match="truncated"):
        pcdmod.read_pcd(path)


def test_truncated_binary_pcd(tmp_path):
    pts, _ = _cloud(10)
    for compressed in (False, True):
        path = tmp_path / f"t{compressed}.pcd"
        write_pcd(path, pts, compressed=compressed)
        data = path.read_bytes()
        path.write_bytes(data[:-5])
        with pytest.raises(InputError, match="truncated") as exc:
            read_scan_file(path)
        assert exc.value.source == str(path)


# ---------------------------------------------------------------- other kinds, errors


def test_bin_round_trip_and_truncated(tmp_path):
    pts, fields = _cloud(100)
    write_bin(tmp_path / "000000.bin", pts, fields["intensity"])
    scan = read_scan_file(tmp_path / "000000.bin")
    np.testing.assert_array_equal(scan.points, pts)
    np.testing.assert_array_equal(scan.intensity, fields["intensity"])
    bad = tmp_path / "000001.bin"
    bad.write_bytes((tmp_path / "000000.bin").read_bytes()[:-3])
    with pytest.raises(InputError, match="multiple of 16") as exc:
        read_scan_file(bad)
    assert exc.value.source == str(bad)
    result = CliRunner().invoke(cli, ["info", str(tmp_path)])
    assert result.exit_code == 2
    assert result.stderr.strip().count("\n") == 0 and str(bad) in result.stderr


def test_empty_scans_name_the_file(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"")
    nan = tmp_path / "n.pcd"
    write_pcd(nan, np.full((4, 3), np.nan, np.float32))
    for path in (tmp_path / "a.bin", nan):
        with pytest.raises(InputError, match="empty scan") as exc:
            read_scan_file(path)
        assert exc.value.source == str(path)
    seq = open_scans(_single(tmp_path, "a.bin"))
    with pytest.raises(InputError, match="empty scan"):
        seq[0]


def _single(tmp_path: Path, name: str) -> Path:
    folder = tmp_path / "one"
    folder.mkdir()
    (folder / name).write_bytes((tmp_path / name).read_bytes())
    return folder


def test_ply_and_numpy(tmp_path):
    pts, fields = _cloud(50)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts))
    cloud.point.intensity = o3d.core.Tensor(fields["intensity"][:, None])
    o3d.t.io.write_point_cloud(str(tmp_path / "a.ply"), cloud)
    scan = read_scan_file(tmp_path / "a.ply")
    np.testing.assert_array_equal(scan.points, pts)
    np.testing.assert_array_equal(scan.intensity, fields["intensity"])
    np.save(tmp_path / "b.npy", np.c_[pts, fields["intensity"]])
    np.testing.assert_array_equal(read_scan_file(tmp_path / "b.npy").intensity, fields["intensity"])
    rec = np.zeros(50, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2")])
    rec["x"], rec["y"], rec["z"], rec["ring"] = pts[:, 0], pts[:, 1], pts[:, 2], fields["ring"]
    np.save(tmp_path / "c.npy", rec)
    np.testing.assert_array_equal(read_scan_file(tmp_path / "c.npy").ring, fields["ring"])
    np.savez(tmp_path / "d.npz", pts=pts)
    np.testing.assert_array_equal(read_scan_file(tmp_path / "d.npz").points, pts)
    np.savez(tmp_path / "e.npz", a=pts, b=pts)
    with pytest.raises(InputError, match="none named 'data'"):
        read_scan_file(tmp_path / "e.npz")
    np.save(tmp_path / "f.npy", pts[:, :2])
    with pytest.raises(InputError, match="N x 3"):
        read_scan_file(tmp_path / "f.npy")
    (tmp_path / "g.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError):
        read_scan_file(tmp_path / "g.npz")


def test_natural_sort_and_lazy_loading(tmp_path):
    pts, _ = _cloud(5)
    names = ["frame10.bin", "frame2.bin", "frame1.bin", "Frame3.bin"]
    for k, name in enumerate(names):
        write_bin(tmp_path / name, pts + k)
    assert [f.name for f in scan_files(tmp_path)] == ["frame1.bin", "frame2.bin", "Frame3.bin", "frame10.bin"]
    assert sorted(["a10b2", "a2b10", "a2b9"], key=natural_key) == ["a2b9", "a2b10", "a10b2"]
    seq = open_scans(tmp_path)
    assert seq.timestamps is None and detect_scan_source(tmp_path) == "folder"
    (tmp_path / "frame10.bin").unlink()  # lazy: nothing read at open
    np.testing.assert_array_equal(seq[1].points, pts + 1)
    with pytest.raises(InputError, match="no such file"):
        seq[3]


def test_numeric_names_sorted_by_value_and_stamped(tmp_path):
    pts, _ = _cloud(5)
    for name in ["1.5", "1.25", "10.0", "2"]:
        write_bin(tmp_path / f"{name}.bin", pts)
    seq = open_scans(tmp_path)
    assert [f.stem for f in seq.meta["files"]] == ["1.25", "1.5", "2", "10.0"]
    np.testing.assert_array_equal(seq.timestamps, [1.25, 1.5, 2.0, 10.0])


@pytest.mark.parametrize("stems, expected", [
    (["1700000000123456789", "1700000000223456789"], [1700000000.123456789, 1700000000.223456789]),  # ns
    (["1700000000123", "1700000000223"], [1700000000.123, 1700000000.223]),  # ms
    (["1700000000.123456", "1700000000.2"], [1700000000.123456, 1700000000.2]),  # ROS seconds
    (["000000", "000001"], None),  # frame numbers
    (["scan_1", "scan_2"], None),
])
def test_stamps_from_names(stems, expected):
    stamps = stamps_from_names([Path(s + ".pcd") for s in stems])
    if expected is None:
        assert stamps is None
    else:
        np.testing.assert_allclose(stamps, expected, rtol=0, atol=1e-6)


def test_times_option_and_times_file(tmp_path):
    pts, _ = _cloud(5)
    for k in range(3):
        write_bin(tmp_path / "scans" / f"{k:06d}.bin", pts)
    (tmp_path / "t.txt").write_text("# stamps\n0.5\n\n0.6\n0.75\n")
    seq = open_scans(tmp_path / "scans", options=ReadOptions(times=tmp_path / "t.txt"))
    np.testing.assert_array_equal(seq.timestamps, [0.5, 0.6, 0.75])
    (tmp_path / "scans" / "times.txt").write_text("1\n2\n")  # count mismatch: ignored
    assert open_scans(tmp_path / "scans").timestamps is None
    (tmp_path / "scans" / "times.txt").write_text("1\n2\n3\n")
    np.testing.assert_array_equal(open_scans(tmp_path / "scans").timestamps, [1, 2, 3])
    (tmp_path / "short.txt").write_text("1\n2\n")
    with pytest.raises(InputError, match="2 times for 3 scans"):
        open_scans(tmp_path / "scans", options=ReadOptions(times=tmp_path / "short.txt"))
    (tmp_path / "bad.txt").write_text("1\nabc\n3\n")
    with pytest.raises(InputError) as exc:
        open_scans(tmp_path / "scans", options=ReadOptions(times=tmp_path / "bad.txt"))
    assert exc.value.line == 2
    (tmp_path / "unsorted.txt").write_text("1\n3\n2\n")
    with pytest.raises(InputError, match="unsorted") as exc:
        open_scans(tmp_path / "scans", options=ReadOptions(times=tmp_path / "unsorted.txt"))
    assert exc.value.line == 3


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(0, 1e10, allow_nan=False), min_size=1, max_size=20, unique=True))
def test_times_file_property(tmp_path, values):
    from dm2_backend.formats.scan_folder import read_times

    values = sorted(values)
    path = tmp_path / "times.txt"
    path.write_text("".join(f"{v!r}\n" for v in values))
    stamps, lines = read_times(path)
    np.testing.assert_array_equal(stamps, values)
    assert lines == list(range(1, len(values) + 1))


def test_mixed_kinds_and_no_scans(tmp_path):
    pts, _ = _cloud(5)
    write_bin(tmp_path / "a.bin", pts)
    write_pcd(tmp_path / "b.pcd", pts)
    with pytest.raises(InputError, match="mixes"):
        open_scans(tmp_path, "folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no scan files"):
        open_scans(empty, "folder")
