"""Preparation plugins on a slice of real data (ACES, CARMEN laser log): the icp warm start beats the raw
odometry on the Freiburg relations, the topology and pairwise registration work on it. Skipped when the
shared data is absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dm2_backend.evaluation.relations import load_relations, relations_error
from dm2_backend.formats import open_scans
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.registration_icp import IcpRegistration
from dm2_backend.plugins.topology_radius import RadiusTopology
from dm2_backend.plugins.warm_start_icp import IcpWarmStart
from dm2_backend.prepare.frames import load_frames

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ACES = DATA / "carmen" / "aces.clf.bz2"
WINDOW = np.arange(4200, 4600)  # 400 of the 7374 scans


@pytest.fixture(scope="module")
def aces():
    if not ACES.exists():
        pytest.skip(f"{ACES} absent")
    seq = open_scans(ACES)
    seq = seq.subset(WINDOW)
    frames = load_frames(seq, max_points=1024, progress=False)
    return seq, frames, load_relations(ACES.with_name("aces.relations"))


def test_aces_icp_warm_start_beats_odometry(aces):
    seq, frames, relations = aces
    odometry = seq.trajectories["odometry"]
    poses = IcpWarmStart(progress=False).run(frames, odometry)
    icp = relations_error(Trajectory(poses, seq.timestamps, planar=True), relations)
    odo = relations_error(odometry, relations)
    assert icp.used == odo.used > 50
    # measured: odometry 0.053 m / 1.69 deg, icp 0.039 m / 0.31 deg (the 62 relations inside the window)
    assert icp.stats["trans_mean"] < 0.9 * odo.stats["trans_mean"]
    assert icp.stats["rot_mean"] < 0.5 * odo.stats["rot_mean"]
    # scan matching alone (constant-velocity prediction; measured 0.047 m / 0.36 deg) is about as good
    alone = IcpWarmStart(prior="velocity", progress=False).run(frames, None)
    alone = relations_error(Trajectory(alone, seq.timestamps, planar=True), relations)
    assert alone.stats["trans_mean"] < 0.06 and alone.stats["rot_mean"] < 0.5
    # radius topology and pairwise registration on the result: almost all local pairs pass the gates
    topo = RadiusTopology(k=4).run(frames, poses)
    pw = IcpRegistration(progress=False).run(frames, poses, topo)
    assert pw.valid.mean() > 0.9
