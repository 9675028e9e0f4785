"""``dm2 convert ... --to kitti --out-times`` on a trajectory with a repeated timestamp (issue 53, item 5): the
times file is written as the trajectory has its stamps, as the conversion without ``--out-times`` accepts
them, and reads back (``--times``) under ``--duplicate-times``."""

from __future__ import annotations

import numpy as np
import pytest
from shared_helpers import DATA, assert_one_line_error, need, run

from dm2_backend.formats import ReadOptions, read_trajectory
from dm2_backend.formats.kitti import read_kitti

TUM = """# timestamp tx ty tz qx qy qz qw
1.0 0 0 0 0 0 0 1
1.5 1 0 0 0 0 0 1
1.5 1.1 0 0 0 0 0 1
2.0 2 0 0 0 0 0 1
"""
EUROC = """#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []
1403715524907143168,0.5,2.0,0.9,1,0,0,0
1403715524912143104,0.6,2.0,0.9,1,0,0,0
1403715524912143104,0.61,2.0,0.9,1,0,0,0
1403715524917143040,0.7,2.0,0.9,1,0,0,0
"""


@pytest.mark.parametrize("name, text", [("t.tum", TUM), ("V102.csv", EUROC)])
def test_convert_times_file_with_repeated_stamps(tmp_path, name, text):
    src = tmp_path / name
    src.write_text(text)
    given = read_trajectory(src)
    assert np.diff(given.timestamps).min() == 0  # the repeat is kept, as evo keeps it
    plain = run("convert", str(src), str(tmp_path / "plain.txt"), "--to", "kitti")
    assert plain.exit_code == 0, plain.output
    result = run("convert", str(src), str(tmp_path / "out.txt"), "--to", "kitti",
                 "--out-times", str(tmp_path / "t.txt"))
    assert result.exit_code == 0, result.output  # as without --out-times
    assert "wrote 4 poses" in result.output
    assert (tmp_path / "out.txt").read_text() == (tmp_path / "plain.txt").read_text()
    written = np.array([float(line) for line in (tmp_path / "t.txt").read_text().splitlines()])
    np.testing.assert_array_equal(written, given.timestamps)  # the repeated stamp written as it is

    # what dm2 writes, dm2 reads: every pose kept (one warning) unless --duplicate-times says otherwise
    back = run("convert", str(tmp_path / "out.txt"), str(tmp_path / "back.tum"), "--from", "kitti",
               "--times", str(tmp_path / "t.txt"))
    assert back.exit_code == 0, back.output
    assert "t.txt: line 3 repeats the timestamp" in back.stderr
    again = read_trajectory(tmp_path / "back.tum")
    np.testing.assert_array_equal(again.timestamps, given.timestamps)
    np.testing.assert_allclose(again.poses, given.poses, atol=1e-12)
    first = read_kitti(tmp_path / "out.txt", ReadOptions(times=tmp_path / "t.txt", duplicate_times="keep-first"))
    assert len(first) == 3 and np.diff(first.timestamps).min() > 0
    np.testing.assert_allclose(first.poses, given.poses[[0, 1, 3]], atol=1e-12)
    refused = run("convert", str(tmp_path / "out.txt"), str(tmp_path / "no.tum"), "--from", "kitti",
                  "--times", str(tmp_path / "t.txt"), "--duplicate-times", "error")
    assert_one_line_error(refused, "t.txt:3")


def test_real_euroc_with_a_repeated_stamp(tmp_path):
    """V102's ground truth with one stamp repeated, as the issue's file has."""
    lines = need(DATA / "trajectories" / "V102_groundtruth.csv").read_text().splitlines()[:201]
    lines[100] = lines[99].split(",")[0] + "," + lines[100].split(",", 1)[1]
    src = tmp_path / "V102.csv"
    src.write_text("\n".join(lines) + "\n")
    result = run("convert", str(src), str(tmp_path / "out.txt"), "--to", "kitti",
                 "--out-times", str(tmp_path / "t.txt"))
    assert result.exit_code == 0, result.output
    written = np.array([float(line) for line in (tmp_path / "t.txt").read_text().splitlines()])
    assert len(written) == 200 and written[98] == written[99]
    np.testing.assert_array_equal(written, read_trajectory(src).timestamps)
