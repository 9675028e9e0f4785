"""The run folder's trajectory files: a CARMEN input is written back as a CARMEN log of the same dialect, the
template log found through the trajectory's own ``carmen_template`` (the key the reader sets)."""

from __future__ import annotations

import numpy as np
from shared_helpers import DATA, need

from dm2_backend.formats import ReadOptions, read_trajectory
from dm2_backend.pipeline import outputs
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.pipeline.run_writer import trajectory_of


def test_a_carmen_run_writes_its_poses_into_a_copy_of_the_log(tmp_path):
    log = need(DATA / "carmen" / "intel.clf.bz2")
    inputs = load_inputs(log, None, None, None, ReadOptions())
    assert inputs.given_format == "carmen"
    moved = inputs.given.poses.copy()
    moved[:, 0, 3] += 0.25
    traj = trajectory_of(moved, inputs)
    assert traj.meta["carmen_template"] == inputs.scans.source
    files = outputs.write_trajectories(tmp_path, traj, inputs.given_path or log, inputs.given_format)
    written = [f for f in files if f.startswith("poses_carmen")]
    assert written == ["poses_carmen.clf.bz2"]
    back = read_trajectory(tmp_path / written[0], "carmen")
    np.testing.assert_allclose(back.positions[:, 0], moved[:, 0, 3], atol=1e-3)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
