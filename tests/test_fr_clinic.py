"""Issue 54 on the real Freiburg hospital log (FR-clinic, ``../shared/data/carmen``): the fused warm start takes no
scan match that slid along a hall as an odometry glitch, and by default (its match cycles find the odometry the more
precise source) it keeps what the precise wheel odometry got right. The first 800 scans (160 m, its first halls and
turns), scored on the log's own relations."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from dm2_backend.evaluation.relations import load_relations, relations_error
from dm2_backend.formats.carmen import open_carmen_scans
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.prepare.frames import load_frames

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"
LOG, RELATIONS = DATA / "fr-clinic_robotlaser.clf.bz2", DATA / "fr-clinic.relations"
SCANS = 800


@pytest.fixture(scope="module")
def clinic():
    if not LOG.exists() or not RELATIONS.exists():
        pytest.skip(f"{LOG} or {RELATIONS} absent")
    seq = open_carmen_scans(LOG)
    frames = load_frames(seq, 1024, progress=False)
    frames = dataclasses.replace(frames, points=frames.points[:SCANS], timestamps=frames.timestamps[:SCANS])
    odometry = seq.trajectories["odometry"]
    odometry = Trajectory(odometry.poses[:SCANS], odometry.timestamps[:SCANS].copy(), planar=True)
    rel = load_relations(RELATIONS)
    last = odometry.timestamps[-1]
    return frames, odometry, rel[(rel[:, 0] <= last) & (rel[:, 1] <= last)]


def error(poses: np.ndarray, odometry: Trajectory, rel: np.ndarray) -> np.ndarray:
    return relations_error(Trajectory(poses, odometry.timestamps.copy(), planar=True), rel).trans_errors


@pytest.mark.parametrize("weigh", ["whole", "auto"])
def test_no_sliding_match_is_taken_as_a_glitch(clinic, weigh):
    frames, odometry, rel = clinic
    ws = IcpWarmStart(weigh=weigh, progress=False)
    poses = ws.run(frames, odometry)
    reasons = ws.report["per_step"]["reason"]
    glitches = [i for i, r in enumerate(reasons) if r.startswith("odometry glitch")]
    departure = [float(np.linalg.norm(se3.relative(se3.relative(odometry.poses[i - 1], odometry.poses[i]),
                                                   se3.relative(poses[i - 1], poses[i]))[:2, 3])) for i in glitches]
    # the odometry moves 0.2 m a scan; matches 0.3-2.6 m off it were taken as glitches before
    assert all(d < 0.3 for d in departure), list(zip(glitches, departure, strict=True))
    if weigh == "whole":  # whole matches meet the gate with the disagreement's spread, and some slide past it
        assert any(r.startswith("the scan match moves") for r in reasons)
    assert len(rel) > 200 and error(poses, odometry, rel).max() < 1.5


def test_cycles_keep_what_the_odometry_got_right(clinic):
    """By default (``weigh: auto``) the match cycles find the odometry the more precise source and weigh the matches
    by themselves: the warm start keeps what the odometry got right, where the whole matches do not."""
    frames, odometry, rel = clinic
    ws = IcpWarmStart(progress=False)
    poses = ws.run(frames, odometry)
    weights = ws.report["match_weights"]["weights"]
    assert max(weights) < 0.5, weights  # the scans disagree among themselves as much as with the odometry
    assert ws.report["match_weights"]["weighed"] == "cycles"
    assert ws.report["settings"]["unjudged_windows"] == "odometry"
    assert "scan matches weighed" in ws.report["summary"]
    whole = IcpWarmStart(weigh="whole", progress=False).run(frames, odometry)
    est, taken = error(poses, odometry, rel), error(whole, odometry, rel)
    assert est.mean() < 0.75 * taken.mean() and est.max() < 0.75 * taken.max(), (est, taken)
    np.testing.assert_array_equal(IcpWarmStart(weigh="cycles", progress=False).run(frames, odometry), poses)
