"""HBA folders (``pcd/<i>.pcd`` + ``pose.json``, tx ty tz qw qx qy qz): the pose file's property round trip, bad
input in one line (exit 2), the folder read as scans plus poses, and a refine on an HBA folder whose
``hba/pose.json`` a reader that follows HBA's own ``mypcl::read_pose`` reads back (issue 53 item 7); BALM's
4x4 ``alidarPose.csv`` read and written as BALM's own ``read_pose`` reads it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from optim_cases import one_thread
from shared_helpers import SMALL_RUN, assert_one_line_error, run

from dm2_backend.formats import ReadOptions, detect_scan_source, detect_trajectory_format, open_scans, read_trajectory
from dm2_backend.formats.balm import write_balm
from dm2_backend.formats.hba import read_hba, write_hba
from dm2_backend.formats.kitti import write_kitti
from dm2_backend.formats.pcd import write_pcd
from dm2_backend.formats.scan_folder import read_scan_file, scan_files
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.pipeline.outputs import aligned_to, write_trajectories
from dm2_backend.pipeline.run_folder import MARKER
from dm2_backend.runtime.errors import InputError


def hba_read_pose(path: Path) -> np.ndarray:
    """HBA's ``mypcl::read_pose`` as written (``while(file >> tx >> ty >> tz >> w >> x >> y >> z)``, then
    ``Eigen::Quaterniond q(w, x, y, z)`` and ``Vector3d t(tx, ty, tz)``; no line structure, reading stops at
    the first token that is not a number), the rotation as Eigen's ``toRotationMatrix`` computes it (which does
    not normalise). Poses (N, 4, 4)."""
    poses = []
    tokens = Path(path).read_text().split()
    for k in range(0, len(tokens) - 6, 7):
        try:
            tx, ty, tz, w, x, y, z = (float(v) for v in tokens[k : k + 7])
        except ValueError:
            break
        T = np.eye(4)
        T[:3, 3] = tx, ty, tz
        twx, twy, twz = 2 * x * w, 2 * y * w, 2 * z * w
        txx, txy, txz = 2 * x * x, 2 * y * x, 2 * z * x
        tyy, tyz, tzz = 2 * y * y, 2 * z * y, 2 * z * z
        T[:3, :3] = [[1 - (tyy + tzz), txy - twz, txz + twy],
                     [txy + twz, 1 - (txx + tzz), tyz - twx],
                     [txz - twy, tyz + twx, 1 - (txx + tyy)]]
        poses.append(T)
    return np.array(poses).reshape(-1, 4, 4)


def hba_write_pose(poses: np.ndarray, path: Path) -> None:
    """HBA's ``mypcl::write_pose``: re-anchored at the first pose, ``std::ostream``'s default 6 significant
    digits, no newline after the last line."""
    rel = se3.inverse(poses[0]) @ poses
    xyz, q = se3.to_xyz_quat(rel, "wxyz")
    path.write_text("\n".join(" ".join(f"{v:g}" for v in (*p, *r)) for p, r in zip(xyz, q, strict=True)))


# ---------------------------------------------------------------------------------------------- pose.json
quat = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
xyz = st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(st.data(), st.integers(1, 20))
def test_pose_json_property_round_trip(tmp_path_factory, data, n):
    """What dm2 writes, dm2 and HBA's reader read back as the same poses (exact float text)."""
    q = np.array(data.draw(st.lists(quat, min_size=n, max_size=n)))
    t = np.array(data.draw(st.lists(xyz, min_size=n, max_size=n)))
    traj = Trajectory(poses=se3.from_xyz_quat(t, q, "wxyz"))
    path = tmp_path_factory.mktemp("hba") / "pose.json"
    write_hba(traj, path)
    back = read_hba(path)
    assert back.timestamps is None and len(back) == n
    tol = 1e-10 * max(1.0, np.abs(t).max())
    np.testing.assert_allclose(back.poses, traj.poses, atol=tol, rtol=0)
    np.testing.assert_allclose(hba_read_pose(path), traj.poses, atol=tol, rtol=0)
    assert detect_trajectory_format(path) == "hba"


def test_reads_what_hba_writes(tmp_path):
    """HBA's own output: 6 significant digits (quaternion norms off by ~1e-6, normalised), no final newline."""
    poses = se3.from_xyz_euler(np.array([[0, 0, 0, 0, 0, 0], [1.5, -2, 0.25, 0.1, -0.2, 0.3],
                                         [3, 1, -0.5, -0.3, 0.05, 2.9]], float))
    path = tmp_path / "pose.json"
    hba_write_pose(poses, path)
    assert not path.read_text().endswith("\n")
    ours = read_trajectory(path)
    assert ours.meta["format"] == "hba"
    np.testing.assert_allclose(ours.poses, hba_read_pose(path), atol=1e-5)
    np.testing.assert_allclose(ours.poses, se3.inverse(poses[0]) @ poses, atol=1e-5)
    np.testing.assert_allclose(se3.rotation_error(ours.poses[:, :3, :3]), 0, atol=1e-12)  # normalised


GOOD = "0 0 0 1 0 0 0\n"


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (GOOD + "1 2 3 1 0 0\n", 2, "6 columns, expected 7"),
        (GOOD + "1 2 nan 1 0 0 0\n", 2, "NaN"),
        (GOOD + "1 2 3 one 0 0 0\n", 2, "not a number: 'one'"),
        (GOOD + "\n1 2 3 0.5 0 0 0\n", 3, "quaternion norm 0.5"),
        (GOOD + "1 2 3 0 0 0 0\n", 2, "quaternion norm 0"),
        ("0 0 0 0 0 0 1 5\n", 1, "8 columns, expected 7"),
    ],
)
def test_bad_line_is_one_line_naming_file_and_line(tmp_path, text, line, problem):
    path = tmp_path / "pose.json"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_hba(path)
    assert info.value.line == line and info.value.source == str(path)
    # through the CLI: an HBA folder whose pose.json is bad stops before any work, exit 2, one line
    (tmp_path / "pcd").mkdir()
    for i in range(text.count("\n")):
        write_pcd(tmp_path / "pcd" / f"{i}.pcd", np.random.default_rng(i).normal(size=(50, 3)))
    out = tmp_path.parent / f"{tmp_path.name}-run"
    result = run("refine", "--scans", str(tmp_path), "--out", str(out), "-q", "--no-cache")
    assert_one_line_error(result, f"{path}:{line}: ")
    assert problem.split(":")[0] in result.stderr
    assert not out.exists()
    assert_one_line_error(run("info", str(path), "--format", "hba"), f"pose.json:{line}")


_TOKEN = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-10, 10).map(str),
                   st.sampled_from(["1e999", "-0", "one", "0x1p3", "#", ",", "1,5", "\u00e9"]))
_LINE = st.lists(_TOKEN, min_size=0, max_size=9).map(" ".join)


@settings(max_examples=60, deadline=None)
@given(st.lists(_LINE, max_size=8).map("\n".join))
def test_any_text_is_poses_or_one_input_error(tmp_path_factory, text):
    """Generated lines of numbers, NaN/inf, huge and broken tokens: valid poses or an InputError, nothing else."""
    path = tmp_path_factory.mktemp("fuzz") / "pose.json"
    path.write_text(text, encoding="utf-8")
    try:
        traj = read_hba(path)
    except InputError as exc:
        assert "\n" not in exc.message
        return
    assert np.isfinite(traj.poses).all() and (se3.rotation_error(traj.poses[:, :3, :3]) < 1e-9).all()


def test_quaternion_close_to_unit_is_normalised(tmp_path):
    path = tmp_path / "pose.json"
    path.write_text("1 2 3 1.004 0 0 0\n4 5 6 0 0 0 0.996\n")
    traj = read_hba(path)
    np.testing.assert_allclose(traj.poses[0], se3.make_poses(np.eye(3), np.array([1.0, 2, 3])), atol=1e-15)
    np.testing.assert_allclose(traj.poses[1, :3, :3], np.diag([-1.0, -1, 1]), atol=1e-15)


def test_convert_to_and_from_pose_json(tmp_path):
    poses = se3.from_xyz_euler(np.array([[0, 0, 0, 0, 0, 0], [1, 2, 3, 0.1, 0.2, 0.3]], float))
    write_kitti(Trajectory(poses=poses), tmp_path / "in.txt")
    made = run("convert", str(tmp_path / "in.txt"), str(tmp_path / "pose.json"))  # .json: HBA
    assert made.exit_code == 0, made.output
    np.testing.assert_allclose(hba_read_pose(tmp_path / "pose.json"), poses, atol=1e-15)
    back = run("convert", str(tmp_path / "pose.json"), str(tmp_path / "back.txt"), "--to", "kitti")
    assert back.exit_code == 0, back.output
    np.testing.assert_allclose(read_trajectory(tmp_path / "back.txt", "kitti").poses, poses, atol=1e-15)


# ------------------------------------------------------------------------------------------ the folder
def hba_folder(root: Path, n: int, names=None, poses: int | None = None) -> Path:
    (root / "pcd").mkdir(parents=True)
    for i, name in enumerate(names or [f"{i}.pcd" for i in range(n)]):
        write_pcd(root / "pcd" / name, np.random.default_rng(i).normal(size=(60, 3)) * 5)
    xyz = np.c_[np.arange(poses or n), np.zeros((poses or n, 2))]
    write_hba(Trajectory(poses=se3.make_poses(np.tile(np.eye(3), (poses or n, 1, 1)), xyz)), root / "pose.json")
    return root


def test_folder_is_scans_plus_poses(tmp_path):
    folder = hba_folder(tmp_path / "hba", 12)
    assert detect_scan_source(folder) == "hba"
    scans = open_scans(folder)
    assert len(scans) == 12 and scans.timestamps is None and scans.meta["pcd_name_fill_num"] == 0
    assert scans.meta["files"][10].name == "10.pcd"  # by number, not by text
    inputs = load_inputs(folder, None, None, None, ReadOptions())
    assert inputs.given_path == folder / "pose.json" and inputs.given_format == "hba"
    np.testing.assert_array_equal(inputs.given.poses[:, 0, 3], np.arange(12))
    # --poses wins over the folder's pose.json
    other = tmp_path / "other.txt"
    write_kitti(Trajectory(poses=se3.identity(12)), other)
    inputs = load_inputs(folder, None, other, None, ReadOptions())
    assert inputs.given_path == other and inputs.given_format == "kitti"
    np.testing.assert_array_equal(inputs.given.poses, se3.identity(12))
    info = run("info", str(folder))
    assert info.exit_code == 0 and "pcd_name_fill_num 0" in info.output, info.output


def test_zero_padded_names(tmp_path):
    folder = hba_folder(tmp_path / "hba", 3, names=["00000.pcd", "00001.pcd", "00002.pcd"])
    assert open_scans(folder).meta["pcd_name_fill_num"] == 5


@pytest.mark.parametrize(
    "names, problem",
    [
        (["0.pcd", "1.pcd", "3.pcd"], "has no scan 2"),
        (["00.pcd", "01.pcd", "2.pcd"], "2.pcd: is not padded as 00.pcd is"),
        (["0.pcd", "1.pcd", "scan.pcd"], "scan.pcd: is not named by its index"),
        (["0.bin", "1.bin"], "holds .bin scans"),
    ],
)
def test_folder_naming_errors(tmp_path, names, problem):
    folder = tmp_path / "hba"
    (folder / "pcd").mkdir(parents=True)
    for name in names:
        if name.endswith(".bin"):
            (folder / "pcd" / name).write_bytes(np.zeros(16, "<f4").tobytes())
        else:
            write_pcd(folder / "pcd" / name, np.ones((4, 3)))
    (folder / "pose.json").write_text(GOOD * len(names))
    with pytest.raises(InputError, match=problem):
        open_scans(folder, "hba")
    assert_one_line_error(run("refine", "--scans", str(folder), "--out", str(tmp_path / "r"), "-q"), problem)


def test_pose_count_must_match_scan_count(tmp_path):
    folder = hba_folder(tmp_path / "hba", 5, poses=4)
    with pytest.raises(InputError, match="4 poses for the 5 scans") as info:
        load_inputs(folder, None, None, None, ReadOptions())
    assert info.value.source == str(folder / "pose.json")


# ------------------------------------------------------------------------------------ refine, round trip
@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


#: the small settings of a test refine, with the dense stage (the default) on
SMALL = {"seed": 3, **SMALL_RUN}


def test_refine_hba_folder_round_trip(tmp_path):
    """An HBA folder made from ``dm2 simulate`` (scans as pcd/<i>.pcd, its drifting warm start as pose.json):
    ``dm2 refine --scans folder`` writes hba/pose.json, which HBA's reader reads as the run's poses, closer to
    the truth than the input; the input folder is left as it was."""
    sim = tmp_path / "sim"
    made = run("simulate", "--planar", "-n", "40", "--seed", "2", "-o", str(sim), "-q")
    assert made.exit_code == 0, made.output
    folder = tmp_path / "hba"
    (folder / "pcd").mkdir(parents=True)
    for i, f in enumerate(scan_files(sim / "velodyne")):
        write_pcd(folder / "pcd" / f"{i}.pcd", read_scan_file(f).points)
    warm = read_trajectory(sim / "warm_start.txt")
    write_hba(warm, folder / "pose.json")
    before = {p.name: p.read_bytes() for p in [folder / "pose.json", *sorted((folder / "pcd").iterdir())]}
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))

    out = tmp_path / "run"
    result = run("refine", "--scans", str(folder), "--out", str(out), "-c", str(tmp_path / "small.yaml"), "-q",
                 "--no-cache")
    assert result.exit_code == 0, result.output + repr(result.exception)

    refined = np.load(out / "poses.npy")
    back = hba_read_pose(out / "hba" / "pose.json")
    assert back.shape == refined.shape == (40, 4, 4)
    np.testing.assert_allclose(back, refined, atol=1e-9, rtol=0)
    np.testing.assert_allclose(read_hba(out / "poses_hba.json").poses, refined, atol=1e-9, rtol=0)
    report = json.loads((out / "report.json").read_text())
    assert "hba/pose.json" in report["files"]
    assert "hba" in json.loads((out / MARKER).read_text())["files"]  # --force replaces it with the rest
    assert before == {p.name: p.read_bytes() for p in [folder / "pose.json", *sorted((folder / "pcd").iterdir())]}

    truth = read_trajectory(sim / "poses.txt").poses[:, :3, 3]

    def ape(poses: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((aligned_to(truth, poses[:, :3, 3]) - truth) ** 2, axis=1))))

    start, end = ape(hba_read_pose(folder / "pose.json")), ape(back)
    assert start > 0.5 and end < 0.1 * start, (start, end)


# ------------------------------------------------------------------------------ BALM's alidarPose.csv
def balm_read_pose(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """BALM 2.0's ``read_pose`` (``benchmark_realworld.cpp``) as written: ``getline`` by line, ``getline(ss, str,
    ',')`` + ``stod`` by field; every fourth line ``aff(j) = nums[j]`` fills an ``Eigen::Matrix4d`` column by
    column, and ``affT = aff.transpose()`` gives the rotation ``affT.block<3,3>(0,0)``, the position
    ``affT.block<3,1>(0,3)`` and the time ``affT(3,3)``. Poses (N, 4, 4) and times (N,)."""
    poses, times, nums = [], [], []
    for order, line in enumerate(Path(path).read_text().splitlines(), start=1):
        nums += [float(s) for s in line.split(",")]
        if order % 4 == 0:
            aff = np.array(nums[:16]).reshape(4, 4, order="F")
            T = np.eye(4)
            T[:3, :] = aff.T[:3, :]
            poses.append(T)
            times.append(aff.T[3, 3])
            nums = []
    return np.array(poses).reshape(-1, 4, 4), np.array(times)


@settings(max_examples=30, deadline=None)
@given(st.data(), st.integers(1, 12), st.booleans())
def test_balm_property_round_trip(tmp_path_factory, data, n, stamped):
    q = np.array(data.draw(st.lists(quat, min_size=n, max_size=n)))
    t = np.array(data.draw(st.lists(xyz, min_size=n, max_size=n)))
    stamps = np.sort(np.array(data.draw(st.lists(st.floats(0, 2e9), min_size=n, max_size=n, unique=True))))
    traj = Trajectory(poses=se3.from_xyz_quat(t, q, "wxyz"), timestamps=stamps if stamped else None)
    path = tmp_path_factory.mktemp("balm") / "alidarPose.csv"
    write_balm(traj, path)
    back = read_trajectory(path)
    assert back.meta["format"] == "balm"
    np.testing.assert_array_equal(back.poses, traj.poses)  # the matrices as written, exactly
    theirs, times = balm_read_pose(path)
    np.testing.assert_array_equal(theirs, traj.poses)
    np.testing.assert_array_equal(times, stamps if stamped else np.arange(n))
    np.testing.assert_array_equal(back.timestamps, times)


def test_balm_plain_4x4_files(tmp_path):
    poses = se3.from_xyz_euler(np.array([[0, 0, 0, 0, 0, 0], [1, 2, 3, 0.1, 0.2, 0.3]], float))
    four = tmp_path / "four.csv"
    four.write_text("".join(" ".join(map(repr, row)) + "\n" for row in poses.reshape(-1, 4).tolist()))
    sixteen = tmp_path / "sixteen.csv"
    sixteen.write_text("".join(",".join(map(repr, T.reshape(16).tolist())) + "\n" for T in poses))
    for path in (four, sixteen):
        traj = read_trajectory(path)
        assert traj.meta["format"] == "balm" and traj.timestamps is None  # last rows 0 0 0 1: no times
        np.testing.assert_array_equal(traj.poses, poses)


@pytest.mark.parametrize(
    "text, line, problem",
    [
        ("1,0,0,0\n0,1,0,0\n0,0,1,0\n0,0,0,0\n1,0,0,0\n", 5, "the last one has 1"),
        ("1,0,0,0\n0,1,0,0\n0,0,1,0\n0,0,0,0\n2,0,0,0\n0,1,0,0\n0,0,1,0\n0,0,0,1\n", 5, "rotation"),
        ("1,0,0,0\n0,1,0,0\n0,0,1,0\n0,0,0,1\n1,0,0,0\n0,1,0,0\n0,0,1,0\n0,0,0,0.5\n", 5, "unsorted"),
        ("1,0,0\n", 1, "3 columns, expected 4 or 16"),
    ],
)
def test_balm_bad_input(tmp_path, text, line, problem):
    path = tmp_path / "alidarPose.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_trajectory(path, "balm")
    assert info.value.line == line
    assert_one_line_error(run("info", str(path), "--format", "balm"), f"alidarPose.csv:{line}")


def test_balm_run_output_in_balms_form(tmp_path):
    """A run given BALM's poses writes its result in BALM's form too (``poses_balm.csv``), with the input's times."""
    poses = se3.from_xyz_euler(np.array([[0, 0, 0, 0, 0, 0], [1, 2, 3, 0.1, 0.2, 0.3]], float))
    given = tmp_path / "alidarPose.csv"
    write_balm(Trajectory(poses=poses, timestamps=np.array([5.0, 5.1])), given)
    written = write_trajectories(tmp_path, Trajectory(poses=poses[::-1], timestamps=np.array([5.0, 5.1])),
                                 given, "balm")
    assert "poses_balm.csv" in written
    theirs, times = balm_read_pose(tmp_path / "poses_balm.csv")
    np.testing.assert_array_equal(theirs, poses[::-1])
    np.testing.assert_array_equal(times, [5.0, 5.1])
