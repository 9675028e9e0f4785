"""A dense input with small gaps (issue 53, item 2): a 100 Hz trajectory with a motion-capture dropout of a few
samples around a 10 Hz scan gives that scan the pose interpolated on SE(3) at its stamp (logged and counted), in
``dm2 refine --poses`` and ``dm2 eval --scans --est``; a wider gap, and any gap of a trajectory not denser than
the scans, is still refused in one line."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml
from optim_cases import one_thread, planar_case
from shared_helpers import SMALL_RUN, one_line_error, run

from dm2_backend.evaluation.map_quality import poses_of_scans
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory, write_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import GAP_PERIODS, Trajectory
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import write_sequence

T0 = 1305031102.175304  # stamps of TUM's size: the association must hold at this precision
N = 12
GAPPED = 5  # the scan with no pose nearby


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """N scans at 10 Hz (random points: association does not look at them) and their times.txt."""
    root = tmp_path_factory.mktemp("dense")
    (root / "velodyne").mkdir()
    rng = np.random.default_rng(0)
    for i in range(N):
        rng.normal(0, 5, (200, 4)).astype(np.float32).tofile(root / "velodyne" / f"{i:06d}.bin")
    (root / "times.txt").write_text("".join(f"{T0 + 0.1 * i!r}\n" for i in range(N)))
    return root


def scan_stamps(folder: Path) -> np.ndarray:
    return np.loadtxt(folder / "times.txt")


def moving(t: np.ndarray) -> np.ndarray:
    """A smooth motion turning about every axis: neighbouring samples differ."""
    s = t - T0
    xyz = np.column_stack([2 * np.sin(s), np.cos(1.3 * s), 0.5 * s])
    return se3.make_poses(se3.rpy_to_matrix(np.column_stack([0.3 * s, -0.2 * s, 2.0 * s])), xyz)


def trajectory(path: Path, period: float, drop: float = 0.0, at: float | None = None) -> Trajectory:
    """A TUM trajectory at ``period`` around the scans' span, without the samples within ``drop`` s of ``at``;
    returned as read back (the reference for the expected poses)."""
    t = T0 + period * np.arange(-1, int(round((0.1 * (N - 1)) / period)) + 2)  # a pose at the first scan's stamp
    if at is not None:
        t = t[np.abs(t - at) > drop]
    write_trajectory(Trajectory(moving(t), t), path, "tum")
    return read_trajectory(path, "tum", ReadOptions())


def inputs(folder: Path, poses: Path):
    return load_inputs(folder / "velodyne", None, poses, "tum", ReadOptions(times=folder / "times.txt"))


def test_a_dropout_of_a_few_samples_is_interpolated_at_the_scan_stamp(folder, tmp_path, caplog):
    at = scan_stamps(folder)[GAPPED]
    traj = trajectory(tmp_path / "mocap.txt", 0.01, drop=0.015, at=at)  # 3 samples gone: poses 0.02 s either side
    with caplog.at_level(logging.INFO, logger="dm2_backend"):
        got = inputs(folder, tmp_path / "mocap.txt")
    assert len(got.given) == len(got.scans) == N
    expected = se3.interpolate(traj.timestamps, traj.poses, np.array([at]))[0]
    np.testing.assert_allclose(got.given.poses[GAPPED], expected, atol=1e-9)
    nearest = traj.poses[np.argmin(np.abs(traj.timestamps - at))]
    assert np.abs(got.given.poses[GAPPED] - nearest).max() > 1e-3  # not the nearest sample's pose
    assert got.given.timestamps[GAPPED] == at
    # every other scan keeps the pose of its own stamp exactly, as without a gap
    others = np.delete(np.arange(N), GAPPED)
    idx = np.searchsorted(traj.timestamps, got.given.timestamps[others])
    np.testing.assert_array_equal(got.given.poses[others], traj.poses[idx])
    assert got.given_full is not None and len(got.given_full) == len(traj)  # the full-rate output still written
    lines = [r.getMessage() for r in caplog.records if "interpolated" in r.getMessage()]
    assert lines == [f"interpolated 1 of {N} scan poses from the trajectory (gaps up to 0.04 s, 4 periods)"]
    assert got.given.meta["interpolated_gaps"]["interpolated"] == 1


def test_eval_scans_interpolates_the_same(folder, tmp_path):
    at = scan_stamps(folder)[GAPPED]
    traj = trajectory(tmp_path / "est.txt", 0.01, drop=0.015, at=at)
    scans = open_scans(folder / "velodyne", None, ReadOptions(times=folder / "times.txt"))
    poses = poses_of_scans(scans, traj, 0.01, tmp_path / "est.txt")
    expected = se3.interpolate(traj.timestamps, traj.poses, np.array([at]))[0]
    np.testing.assert_allclose(poses[GAPPED], expected, atol=1e-9)
    r = run("eval", "--scans", folder / "velodyne", "--scans-times", folder / "times.txt", "--est",
            tmp_path / "est.txt", "--json", tmp_path / "eval.json")
    assert r.exit_code == 0, r.output
    assert f"interpolated 1 of {N} scan poses from the trajectory" in r.output
    assert np.isfinite(json.loads((tmp_path / "eval.json").read_text())["estimates"][0]["metrics"]["map"]["entropy"])


def test_a_gap_wider_than_the_limit_is_refused_in_one_line(folder, tmp_path):
    at = scan_stamps(folder)[GAPPED]
    wide = max(0.01 * GAP_PERIODS, 0.1) + 0.015  # nearest poses 12 periods either side: past one scan period
    trajectory(tmp_path / "gap.txt", 0.01, drop=wide, at=at)
    r = run("refine", "--scans", folder / "velodyne", "--times", folder / "times.txt", "--poses",
            tmp_path / "gap.txt", "--out", tmp_path / "run")
    one_line_error(r, f"only {N - 3} of {N} scans have a pose within 0.01 s", "--max-diff")
    r = run("eval", "--scans", folder / "velodyne", "--scans-times", folder / "times.txt", "--est",
            tmp_path / "gap.txt")
    one_line_error(r, f"only {N - 3} of {N} scans have a pose within 0.01 s")


def test_one_sided_gaps_are_refused(folder, tmp_path):
    """The last scan past the trajectory's end: no pose after it, nothing to interpolate between."""
    t = T0 - 0.05 + 0.01 * np.arange(int(round((0.1 * (N - 1)) / 0.01)) + 2)  # ends 0.04 s before the last scan
    write_trajectory(Trajectory(moving(t), t), tmp_path / "short.txt", "tum")
    with pytest.raises(InputError, match=f"only {N - 1} of {N} scans have a pose"):
        inputs(folder, tmp_path / "short.txt")


@pytest.mark.parametrize("period", [0.2, 0.0999])
def test_gaps_of_a_trajectory_not_denser_than_the_scans_are_not_bridged(folder, tmp_path, period):
    """5 Hz poses for 10 Hz scans (every other scan between two poses one period apart), and 10 Hz poses whose
    period is shorter than the scans' only by clock jitter, missing one pose: refused as before."""
    at = scan_stamps(folder)[GAPPED]
    trajectory(tmp_path / "sparse.txt", period, drop=0.005, at=at)
    with pytest.raises(InputError, match="scans have a pose within 0.01 s"):
        inputs(folder, tmp_path / "sparse.txt")


def test_refine_records_the_interpolated_poses(tmp_path):
    """End to end: the run goes through, logs the line and counts the poses in report.json."""
    case = planar_case()
    seq = tmp_path / "seq"
    write_sequence(seq, case.scans, case.gt, case.warm, 10.0)
    stamps = np.arange(len(case.scans)) * 0.1
    fine = np.arange(0.0, stamps[-1] + 0.05, 0.01)
    fine = fine[np.abs(fine - stamps[3]) > 0.015]  # a dropout of 3 samples at scan 3
    dense = Trajectory(se3.interpolate(stamps, case.warm, fine), fine, planar=True)
    write_trajectory(dense, tmp_path / "mocap.txt", "tum")
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL_RUN))
    out = tmp_path / "run"
    r = run("refine", "--scans", seq / "velodyne", "--poses", tmp_path / "mocap.txt", "--out", out, "-c",
            tmp_path / "small.yaml", "--epochs", "1", "--no-cache")
    assert r.exit_code == 0, r.output + repr(r.exception)
    assert f"interpolated 1 of {len(case.scans)} scan poses from the trajectory" in r.output
    report = json.loads((out / "report.json").read_text())
    assert report["interpolated_gaps"]["interpolated"] == 1 and report["interpolated_gaps"]["of"] == len(case.scans)
