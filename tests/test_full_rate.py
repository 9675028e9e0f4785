"""The input trajectory at its own rate, corrected (``poses_full_rate_*``): a 100 Hz trajectory with 10 Hz
scans and a known smooth drift is brought back to the truth at every stamp, a pure re-anchoring changes
nothing, and ``dm2 refine`` writes it end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case
from shared_helpers import SMALL_RUN

from dm2_backend.cli.main import cli
from dm2_backend.formats import ReadOptions, read_trajectory, write_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.full_rate import corrected_full_rate
from dm2_backend.simulate.sequence import write_sequence


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def truth_100hz(seconds: float = 20.0) -> Trajectory:
    """A 3D path at 100 Hz: a loop with a climb, turning, rolling and pitching a little."""
    t = np.arange(0.0, seconds, 0.01)
    xyz = np.column_stack([10 * np.sin(0.3 * t), 8 * (1 - np.cos(0.3 * t)), 0.1 * t])
    rpy = np.column_stack([0.05 * np.sin(t), 0.03 * np.cos(0.7 * t), 0.3 * t])
    return Trajectory(se3.make_poses(se3.rpy_to_matrix(rpy), xyz), t)


def drift(t: np.ndarray) -> np.ndarray:
    """A smooth world-frame drift growing with time: yaw 0.5 deg/s, 2 cm/s, a slow tilt."""
    rpy = np.column_stack([0.001 * t, 0.0005 * t, np.deg2rad(0.5) * t])
    return se3.make_poses(se3.rpy_to_matrix(rpy), np.column_stack([0.02 * t, -0.01 * t, 0.002 * t**2]))


def errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)


def test_a_smooth_drift_is_removed_at_every_stamp_to_the_accuracy_of_the_scan_poses():
    truth = truth_100hz()
    given = truth.with_poses(drift(truth.timestamps) @ truth.poses)
    scans = np.arange(25, len(truth) - 40, 10)  # 10 Hz scans, the input starting before and ending after them
    rng = np.random.default_rng(0)
    noise = se3.make_poses(se3.rpy_to_matrix(rng.normal(0, 1e-4, (len(scans), 3))),
                           rng.normal(0, 1e-3, (len(scans), 3)))
    refined = truth.poses[scans] @ noise  # the scan poses as a refine returns them: the truth, to ~1 mm
    out = corrected_full_rate(given, given.subset(scans), refined)
    assert len(out.trajectory) == len(truth)
    assert np.array_equal(out.trajectory.timestamps, truth.timestamps)
    inside = (truth.timestamps >= truth.timestamps[scans[0]]) & (truth.timestamps <= truth.timestamps[scans[-1]])
    assert out.outside == int((~inside).sum()) == scans[0] + len(truth) - 1 - scans[-1]
    err = errors(out.trajectory.poses, truth.poses)
    scan_err = errors(refined, truth.poses[scans]).max()
    assert errors(given.poses, truth.poses).max() > 1.0  # the input is metres off
    assert err[inside].max() < scan_err + 1e-3, (err[inside].max(), scan_err)
    rot = se3.rotation_angle(se3.relative(out.trajectory.poses, truth.poses)[:, :3, :3])[inside]
    assert np.rad2deg(rot.max()) < 0.05
    # at the scans' own stamps the output is the refined scan pose itself
    assert np.allclose(out.trajectory.poses[scans], refined, atol=1e-9)
    # outside the span the nearest correction: the error stays that of the end scan, not the drift's
    assert err[~inside].max() < 0.05


def test_a_pure_re_anchoring_changes_nothing_but_the_anchor():
    truth = truth_100hz(5.0)
    scans = np.arange(0, len(truth), 10)
    anchor = se3.make_poses(se3.rpy_to_matrix(np.array([0.1, -0.2, 2.0])), np.array([100.0, -50.0, 3.0]))
    out = corrected_full_rate(truth, truth.subset(scans), anchor @ truth.poses[scans])
    assert np.allclose(out.trajectory.poses, anchor @ truth.poses, atol=1e-9)
    assert out.outside == len(truth) - 1 - scans[-1]  # the re-anchoring holds outside the span too


def test_refine_writes_the_input_at_its_own_rate(tmp_path):
    case = planar_case()
    seq = tmp_path / "seq"
    write_sequence(seq, case.scans, case.gt, case.warm, 10.0)
    stamps = np.arange(len(case.scans)) * 0.1
    fine = np.arange(0.0, stamps[-1] + 0.05, 0.01)  # 100 Hz, half a scan period past the last scan
    dense = Trajectory(se3.interpolate(stamps, case.warm, fine), fine, planar=True)
    write_trajectory(dense, tmp_path / "lio_100hz.txt", "tum")
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL_RUN))
    out = tmp_path / "run"
    result = CliRunner().invoke(cli, ["refine", "--scans", str(seq / "velodyne"), "--poses",
                                      str(tmp_path / "lio_100hz.txt"), "--out", str(out), "-c",
                                      str(tmp_path / "small.yaml"), "--epochs", "1", "-q", "--no-cache"], obj={})
    assert result.exit_code == 0, result.output + repr(result.exception)
    full = read_trajectory(out / "poses_full_rate_tum.txt", "tum", ReadOptions())
    scans = read_trajectory(out / "poses_tum.txt", "tum", ReadOptions())
    assert np.allclose(full.timestamps, fine)
    at_scans = np.searchsorted(fine, scans.timestamps - 1e-6)
    assert np.allclose(full.poses[at_scans], scans.poses, atol=1e-6)
    report = json.loads((out / "report.json").read_text())
    assert report["full_rate"] == {"poses": len(fine), "outside_scans_span": 4}
    assert "poses_full_rate_tum.txt" in report["files"]
