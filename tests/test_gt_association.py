"""Ground truth associated with the scans by time, as evo does: a faster ground truth, and scans without a
ground-truth pose nearby, are evaluated on the matched pairs (and say how many matched)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from optim_cases import one_thread, planar_case

from dm2_backend.cli.main import cli
from dm2_backend.evaluation.paper_ate import paper_ate
from dm2_backend.formats import ReadOptions, read_trajectory, write_trajectory
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.runtime.errors import InputError
from dm2_backend.simulate.sequence import write_sequence

RATE = 10.0
T0 = 1305031102.175304


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    """A scan folder at 10 Hz with its times.txt, and a TUM ground truth at 100 Hz that has nothing within
    0.02 s of scan 7 (like a TUM RGB-D frame at a gap of the motion capture)."""
    case = planar_case()
    root = tmp_path_factory.mktemp("seq")
    write_sequence(root, case.scans, case.gt, case.warm, RATE)
    n = len(case.scans)
    stamps = T0 + np.arange(n) / RATE
    (root / "times.txt").write_text("".join(f"{float(t)!r}\n" for t in stamps))
    fine = T0 + np.arange(0, (n - 1) * 10 + 1) / (10 * RATE)
    keep = np.abs(fine - stamps[7]) > 0.025
    # the poses at 100 Hz: the frame's pose at the frame's stamp, a small step beside it in between
    idx = np.clip(np.round((fine - T0) * RATE).astype(int), 0, n - 1)
    poses = case.gt[idx].copy()
    poses[:, 0, 3] += (fine - stamps[idx]) * 0.5
    write_trajectory(Trajectory(poses[keep], fine[keep]), root / "groundtruth.txt", "tum")
    (root / "config.yaml").write_text(yaml.safe_dump({"seed": 1, "frames": {"max_points": 128}, "optimiser": {
        "points_per_frame": 32, "bce_points_per_frame": 16, "batch_groups": 16, "grid_max_cells": 2**12}}))
    return root


def inputs_of(seq: Path, max_diff: float = 0.01):
    return load_inputs(seq / "velodyne", None, seq / "warm_start.txt", "kitti",
                       ReadOptions(times=seq / "times.txt"), seq / "groundtruth.txt", "tum", max_diff=max_diff)


def test_a_faster_ground_truth_is_matched_by_time(seq, caplog):
    inputs = inputs_of(seq)
    n = len(inputs.scans)
    assert len(inputs.gt) == n - 1 and 7 not in inputs.gt_frames
    np.testing.assert_array_equal(inputs.gt_frames, np.delete(np.arange(n), 7))
    # each scan got the ground-truth pose at its own stamp, not a neighbour 10 ms away
    np.testing.assert_allclose(inputs.gt.timestamps, inputs.scans.timestamps[inputs.gt_frames], atol=1e-6)
    assert "ground truth for %d of %d scans" in caplog.records[-1].msg
    assert caplog.records[-1].args[1:3] == (n - 1, n)


def test_no_match_within_max_diff_is_one_line(seq, tmp_path):
    shifted = tmp_path / "late.txt"
    lines = [ln for ln in (seq / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")]
    shifted.write_text("".join(f"{float(ln.split()[0]) + 3600:.6f} {' '.join(ln.split()[1:])}\n" for ln in lines))
    with pytest.raises(InputError, match="no ground-truth stamp within 0.01 s"):
        load_inputs(seq / "velodyne", None, seq / "warm_start.txt", "kitti", ReadOptions(times=seq / "times.txt"),
                    shifted, "tum")


def test_refine_evaluates_the_matched_scans(seq, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(cli, ["refine", "--scans", str(seq / "velodyne"), "--poses",
                                      str(seq / "warm_start.txt"), "--times", str(seq / "times.txt"), "--gt",
                                      str(seq / "groundtruth.txt"), "-c", str(seq / "config.yaml"), "--epochs", "1",
                                      "--no-cache", "-q", "--out", str(out)], obj={})
    assert result.exit_code == 0, result.output + repr(result.exception)
    report = json.loads((out / "report.json").read_text())
    inputs = inputs_of(seq)
    assert report["ground_truth_scans"] == len(inputs.scans) - 1
    warm = read_trajectory(seq / "warm_start.txt", "kitti").poses
    expected = paper_ate(inputs.gt.poses, warm[inputs.gt_frames]).trans
    assert report["warm_start_metrics"]["paper_ate_trans"] == pytest.approx(expected, rel=1e-9)
