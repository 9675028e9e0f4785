"""TUM and EuRoC: agreement with evo, exact timestamps, property round trips, bad input, CLI."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_helpers import DATA, assert_one_line_error, need, run

from dm2_backend.formats import ReadOptions, detect_trajectory_format, read_trajectory
from dm2_backend.formats.euroc import read_euroc
from dm2_backend.formats.g2o import read_g2o
from dm2_backend.formats.tum import read_tum, write_tum
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

TRAJ = DATA / "trajectories"
TUM_FILES = ["fr2_desk_ORB.txt", "freiburg1_xyz-ORB_kf_mono.txt", "freiburg1_xyz-groundtruth.txt",
             "freiburg1_xyz-rgbdslam.txt"]


@pytest.mark.parametrize("name", TUM_FILES)
def test_tum_agrees_with_evo(name):
    from evo.tools.file_interface import read_tum_trajectory_file

    path = need(TRAJ / name)
    assert detect_trajectory_format(path) == "tum"
    ours = read_trajectory(path)
    theirs = read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(ours.timestamps, theirs.timestamps)
    np.testing.assert_allclose(ours.poses, np.array(theirs.poses_se3), atol=1e-9, rtol=0)


def test_tum_duplicate_stamp_in_real_groundtruth(caplog, tmp_path):
    """fr2_desk ground truth repeats 1311868229.5760 (lines 10862-10863): read as evo reads it, every pose
    kept, with one warning; refused or thinned only when asked."""
    from evo.tools.file_interface import read_tum_trajectory_file

    path = need(TRAJ / "fr2_desk_groundtruth.txt")
    theirs = read_tum_trajectory_file(str(path))
    with caplog.at_level("WARNING", logger="dm2_backend.formats"):
        ours = read_trajectory(path)
    (record,) = caplog.records
    assert "line 10863 repeats the timestamp 1311868229.576 of line 10862" in record.getMessage()
    assert ours.meta["duplicate_lines"] == [10863]
    np.testing.assert_array_equal(ours.timestamps, theirs.timestamps)
    np.testing.assert_allclose(ours.poses, np.array(theirs.poses_se3), atol=1e-9, rtol=0)
    with pytest.raises(InputError, match="duplicate timestamp 1311868229.576") as info:
        read_tum(path, ReadOptions(duplicate_times="error"))
    assert info.value.line == 10863
    first = read_tum(path, ReadOptions(duplicate_times="keep-first"))
    assert first.meta["dropped_duplicate_lines"] == [10863]
    keep = np.ones(len(theirs.timestamps), bool)
    keep[10863 - 4] = False  # three comment lines, 1-based line numbers
    np.testing.assert_array_equal(first.timestamps, theirs.timestamps[keep])
    back = tmp_path / "back.txt"
    back.write_text("0 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="unsorted") as info:  # a step back in time stays an error
        read_tum(back)
    assert info.value.line == 4


def test_eval_with_repeated_ground_truth_stamp_equals_evo(tmp_path):
    """`dm2 eval` on fr2_desk without a flag: one warning line, and the APE of evo_ape tum gt est -a."""
    import json

    from evo.core import metrics, sync
    from evo.tools.file_interface import read_tum_trajectory_file

    gt, est = need(TRAJ / "fr2_desk_groundtruth.txt"), need(TRAJ / "fr2_desk_ORB.txt")
    out = tmp_path / "eval.json"
    result = run("eval", "--gt", str(gt), "--est", str(est), "--align", "se3", "--json", str(out))
    assert result.exit_code == 0, result.output
    warnings = [ln for ln in result.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "line 10863" in warnings[0]
    ref, traj = sync.associate_trajectories(read_tum_trajectory_file(str(gt)), read_tum_trajectory_file(str(est)))
    traj.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    mine = json.loads(out.read_text())["estimates"][0]["metrics"]["ape_trans"]
    assert mine["rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-9)


def test_euroc_agrees_with_evo():
    from evo.tools.file_interface import read_euroc_csv_trajectory

    path = need(TRAJ / "V102_groundtruth.csv")
    assert detect_trajectory_format(path) == "euroc"
    ours = read_trajectory(path)
    theirs = read_euroc_csv_trajectory(str(path))
    assert len(ours) == 16702 and ours.meta["columns"] == 17
    np.testing.assert_allclose(ours.timestamps, theirs.timestamps, rtol=1e-15, atol=0)
    np.testing.assert_allclose(ours.poses, np.array(theirs.poses_se3), atol=1e-9, rtol=0)


def test_euroc_eight_columns_and_plain_header(tmp_path):
    path = need(TRAJ / "V102_groundtruth.csv")
    lines = path.read_text().splitlines()[1:101]
    short = tmp_path / "state.csv"
    rows = "\n".join(",".join(r.split(",")[:8]) for r in lines)
    short.write_text("timestamp,px,py,pz,qw,qx,qy,qz\n" + rows)
    full = tmp_path / "full.csv"
    full.write_text("\n".join([path.read_text().splitlines()[0], *lines]) + "\n")
    a, b = read_euroc(short), read_euroc(full)
    assert a.meta["columns"] == 8 and len(a) == 100
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    assert a.timestamps[0] == 1403715524907143168 / 10**9


quat = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
xyz = st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3)
stamps = st.lists(st.floats(0, 2e9, allow_subnormal=False), min_size=1, max_size=20, unique=True)


@settings(max_examples=40, deadline=None)
@given(stamps, st.data())
def test_tum_property_write_read(tmp_path_factory, times, data):
    n = len(times)
    q = np.array(data.draw(st.lists(quat, min_size=n, max_size=n)))
    t = np.array(data.draw(st.lists(xyz, min_size=n, max_size=n)))
    traj = Trajectory(poses=se3.from_xyz_quat(t, q, "xyzw"), timestamps=np.sort(times))
    out = tmp_path_factory.mktemp("t") / "p.txt"
    write_tum(traj, out)
    back = read_tum(out)
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)  # never rounded
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-10 * max(1.0, np.abs(t).max()), rtol=0)


GOOD = "1.0 0 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (GOOD + "2.0 0 0 0 0 0 1\n", 2, "7 columns, expected 8"),
        ("# h\n" + GOOD + "2.0 0 nan 0 0 0 0 1\n", 3, "NaN"),
        (GOOD + "2.0 0 0 0 0 0 0 0.5\n", 2, "quaternion norm 0.5"),
        (GOOD + "2.0 0 0 0 0 0 0 0\n", 2, "quaternion norm 0"),
        (GOOD + "0.5 0 0 0 0 0 0 1\n", 2, "unsorted timestamp 0.5 after 1.0"),
        (GOOD + "2.0 0 0 0 0 0 0 one\n", 2, "not a number: 'one'"),
        ("# only a comment\n", None, "no timestamp"),
    ],
)
def test_tum_bad_input(tmp_path, text, line, problem):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_tum(path)
    assert info.value.line == line and info.value.source == str(path)
    assert_one_line_error(run("info", str(path), "--format", "tum"), "bad.txt")
    out = str(tmp_path / "o.g2o")
    assert_one_line_error(run("convert", str(path), out, "--from", "tum"), "bad.txt")


HEADER = "#timestamp,px,py,pz,qw,qx,qy,qz\n"


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (HEADER + "1000,0,0,0,1,0,0,0\n2000,0,0,0,1,0,0\n", 3, "7 columns"),
        (HEADER + "1000,0,0,0,1,0,0,0\n1000.5,0,0,0,1,0,0,0\n", 3, "not whole nanoseconds"),
        (HEADER + "2000,0,0,0,1,0,0,0\n1000,0,0,0,1,0,0,0\n", 3, "unsorted"),
        (HEADER + "1000,0,0,0,1,0,0,0\n2000,0,0,0,2,0,0,0\n", 3, "quaternion norm 2"),
        (HEADER + "1000,0,0,inf,1,0,0,0\n", 2, "NaN"),
        (HEADER, None, "no pose lines"),
    ],
)
def test_euroc_bad_input(tmp_path, text, line, problem):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as info:
        read_euroc(path)
    assert info.value.line == line
    assert_one_line_error(run("info", str(path), "--format", "euroc"), "bad.csv")


def test_missing_and_binary_files(tmp_path):
    for reader in (read_tum, read_euroc):
        with pytest.raises(InputError, match="no such file"):
            reader(tmp_path / "nope.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x01" * 10)
    with pytest.raises(InputError, match="not a text file"):
        read_tum(tmp_path / "bin.txt")


def test_cli_convert_tum_to_g2o_and_euroc_to_tum(tmp_path):
    src = need(TRAJ / "freiburg1_xyz-groundtruth.txt")
    out = tmp_path / "gt.g2o"
    result = run("convert", str(src), str(out))
    assert result.exit_code == 0, result.output
    graph = read_g2o(out)
    tum = read_tum(src)
    np.testing.assert_allclose(graph.poses, tum.poses, atol=1e-12)
    assert len(graph.edges) == len(tum) - 1 and not graph.planar
    euroc = need(TRAJ / "V102_groundtruth.csv")
    out = tmp_path / "v102.txt"
    assert run("convert", str(euroc), str(out), "--to", "tum").exit_code == 0
    back = read_tum(out)
    np.testing.assert_array_equal(back.timestamps, read_euroc(euroc).timestamps)
    refused = run("convert", str(src), str(tmp_path / "x.csv"), "--to", "euroc")
    assert_one_line_error(refused, "x.csv")
    assert "cannot be written" in refused.stderr
    ambiguous = run("convert", str(src), str(tmp_path / "x.txt"))
    assert_one_line_error(ambiguous, "x.txt")


def test_sniffing_tells_tum_from_look_alikes(tmp_path):
    tum = tmp_path / "a.tum"
    tum.write_text("# t x y z qx qy qz qw\n1.5 0 0 0 0 0 0 1\n")
    assert detect_trajectory_format(tum) == "tum"
    relations = tmp_path / "relations.txt"  # t1 t2 x y z roll pitch yaw: 8 columns, not quaternions
    relations.write_text("1.0 2.0 0.5 0.1 0 0 0 0.3\n")
    with pytest.raises(InputError, match="format"):
        detect_trajectory_format(relations)
    spaced = tmp_path / "spaced.csv"  # 8 numbers without commas is not EuRoC
    spaced.write_text("1000 0 0 0 1 0 0 0\n")
    with pytest.raises(InputError, match="format"):
        detect_trajectory_format(spaced)
