"""The consistency profile (no ground truth): on poses broken on purpose it flags the broken stretch and nothing
far from it (a 0.3 m / 2 deg jump at one frame, a jump that carries on, a drifting stretch, a wrong loop
closure forced into a pose graph), and nothing on the true poses; its files and plot hold what it computed."""

from __future__ import annotations

import csv
import json
from functools import lru_cache

import numpy as np
import pytest
from optim_cases import one_thread
from shared_helpers import DATA, need, run

from dm2_backend.evaluation import consistency_profile as cp
from dm2_backend.evaluation import plots
from dm2_backend.evaluation.consistency_profile import GAP, consistency_profile, write_profiles
from dm2_backend.formats import ReadOptions, write_trajectory
from dm2_backend.geometry import se3
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.scans import Scan, ScanSequence
from dm2_backend.simulate.broken import (
    broken_frames,
    bump,
    drifting,
    hits_and_false_flags,
    jump_from,
    one_frame,
    wrong_closure,
)
from dm2_backend.simulate.sequence import SimSettings, simulate, write_sequence
from dm2_backend.trajectory import Trajectory

KEYFRAMES = DATA / "lidar3d" / "balm_realworld_000-079"


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@lru_cache(maxsize=1)
def street() -> tuple[list[np.ndarray], ScanSequence, np.ndarray]:
    """80 frames of the simulated 32-beam LiDAR street (2 cm range noise, 1.5 laps) and the true poses."""
    scans, gt, _ = simulate(SimSettings(frames=80, seed=3, extent=10.0, laps=1.5), progress=False)
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), timestamps=np.arange(len(scans)) * 0.1, planar=False)
    return scans, seq, gt


@lru_cache(maxsize=1)
def keyframes() -> tuple[ScanSequence, np.ndarray]:
    need(KEYFRAMES / "poses.txt")
    real = load_inputs(KEYFRAMES / "velodyne", None, KEYFRAMES / "poses.txt", None,
                       ReadOptions(times=KEYFRAMES / "times.txt"))
    return real.scans, real.given.poses


def flags(p, truth: np.ndarray, poses: np.ndarray) -> tuple[bool, int]:
    """Hits and false flags of profile ``p``, within the profile's own resolution (a stretch and a gap)."""
    return hits_and_false_flags(p.flagged, broken_frames(truth, poses), p.window + GAP)


def profile(seq: ScanSequence, poses: np.ndarray):
    return consistency_profile(seq, poses, seq.timestamps)


def test_the_true_poses_of_the_simulated_street_raise_no_flag():
    _, seq, gt = street()
    p = profile(seq, gt)
    assert p.segments == [], p.segments
    assert np.isfinite(p.score_m).all()
    assert p.level_m < 0.03  # 2 cm range noise: the frames agree at the sensor's noise


@pytest.mark.parametrize("break_it", ["one frame", "jump", "drift"])
def test_a_broken_stretch_of_the_street_is_flagged_and_nothing_far_from_it(break_it):
    _, seq, gt = street()
    poses = {"one frame": lambda: one_frame(gt, 40), "jump": lambda: jump_from(gt, 40),
             "drift": lambda: drifting(gt, 40, 10)}[break_it]()
    p = profile(seq, poses)
    hit, false = flags(p, gt, poses)
    assert hit and false == 0, (p.segments, false)


@pytest.mark.parametrize("poses_of", ["truth", "jump"])
def test_a_sequence_longer_than_the_cell_budget_is_judged_a_stretch_at_a_time(monkeypatch, poses_of):
    """A budget of 8 frames' cells for 80 frames (as 1.5 million cells for 10,000 frames, where 150 cells a
    frame flagged half the true frames): the scans are read again in stretches at full density, so the truth
    scores as with every cell (no flag, each view's median within 15 %) and a jump is still found, nothing
    far from it."""
    _, seq, gt = street()
    full = profile(seq, gt)
    monkeypatch.setattr(cp, "MAX_CELLS", 8 * cp.CELLS_PER_FRAME)
    poses = gt if poses_of == "truth" else jump_from(gt, 40)
    p = profile(seq, poses)
    assert np.isfinite(p.score_m).all()
    if poses_of == "truth":
        assert p.segments == [], p.segments
        for view in ("all", "past", "future"):
            assert np.nanmedian(p.views_m[view]) == pytest.approx(np.nanmedian(full.views_m[view]), rel=0.15), view
    else:
        hit, false = flags(p, gt, poses)
        assert hit and false == 0, (p.segments, false)


def test_a_wrong_loop_closure_forced_into_a_pose_graph_is_flagged_where_it_bent_the_path():
    """The street's pose graph from the truth (odometry and every pair within 3 m) plus one closure between
    frames 2 and 53 that claims 1 m and 5 degrees more than the truth: gtsam bends both ends."""
    _, seq, gt = street()
    bent = wrong_closure(gt, 2, 53, bump(1.0, 5.0), radius=3.0)
    broken = broken_frames(gt, bent)
    assert broken[2] and broken[53]  # the closure did bend the path at its two ends
    p = profile(seq, bent)
    hit, false = flags(p, gt, bent)
    assert hit and false == 0, (p.segments, np.flatnonzero(broken))
    assert {2, 53} <= set(np.flatnonzero(p.flagged))


def test_the_real_keyframes_front_end_poses_raise_no_flag():
    seq, poses = keyframes()
    p = profile(seq, poses)
    assert p.segments == [], p.segments


@pytest.mark.parametrize("break_it", ["one frame", "jump"])
def test_a_jump_in_the_real_keyframes_is_flagged_and_nothing_far_from_it(break_it):
    seq, poses = keyframes()
    broken_poses = one_frame(poses, 40) if break_it == "one frame" else jump_from(poses, 40)
    p = profile(seq, broken_poses)
    hit, false = flags(p, poses, broken_poses)
    assert hit and false == 0, p.segments
    assert p.flagged[40]


def test_files_and_plot_hold_the_profile(tmp_path):
    _, seq, gt = street()
    profiles = {"truth": profile(seq, gt), "broken": profile(seq, one_frame(gt, 40))}
    names = write_profiles(tmp_path, profiles, gt[:, :3, 3], steps={"held": [39, 40], "contradicted": []})
    assert names == ["consistency.json", "consistency.csv", "consistency.png"]
    doc = json.loads((tmp_path / "consistency.json").read_text())
    assert doc["steps"] == {"held": [39, 40], "contradicted": []}  # the step guard's decisions beside the scores
    assert np.allclose(doc["broken"]["score_m"], profiles["broken"].score_m)
    assert doc["broken"]["segments"][0]["first"] <= 40 <= doc["broken"]["segments"][0]["last"]
    rows = list(csv.DictReader((tmp_path / "consistency.csv").open()))
    assert len(rows) == len(gt)
    assert [int(r["broken_flagged"]) for r in rows] == profiles["broken"].flagged.astype(int).tolist()
    assert float(rows[40]["stamp_s"]) == pytest.approx(4.0)
    assert [i for i, r in enumerate(rows) if r["step_held"] == "1"] == [39, 40]
    assert not any(r["step_contradicted"] == "1" for r in rows)
    fig = plots.consistency_figure(gt[:, :3, 3], profiles)
    top, series = fig.axes[0], fig.axes[2]  # the colour bar is axes[1]
    assert np.allclose(top.collections[0].get_offsets(), gt[:, :2, 3])  # x-y top view of the given positions
    assert np.allclose(top.collections[0].get_array(), profiles["broken"].score_m)
    lines = [ln for ln in series.get_lines() if len(ln.get_xdata()) == len(gt)]
    assert np.allclose(lines[-1].get_ydata(), profiles["broken"].score_m)
    assert series.get_xlim() == (-0.5, len(gt) - 0.5) and series.get_ylim()[0] == 0.0
    assert series.get_ylim()[1] >= np.nanmax(profiles["broken"].score_m)


def test_eval_writes_the_profile_and_names_the_flagged_frames(tmp_path):
    scans, _, gt = street()
    write_sequence(tmp_path / "seq", scans, gt, one_frame(gt, 40), 10.0)
    result = run("eval", "--scans", str(tmp_path / "seq" / "velodyne"), "--est", str(tmp_path / "seq" / "poses.txt"),
                 "--est", str(tmp_path / "seq" / "warm_start.txt"), "--est-times", str(tmp_path / "seq" / "times.txt"),
                 "--profile", str(tmp_path / "profile"))
    assert result.exit_code == 0, result.output
    lines = [ln for ln in result.output.splitlines() if ln.startswith("consistency:")]
    assert "poses: " in lines[0] and lines[0].endswith("none")
    assert "warm_start: " in lines[1] and "peak" in lines[1] and " at 40" in lines[1], lines
    assert {p.name for p in (tmp_path / "profile").iterdir()} == {"consistency.json", "consistency.csv",
                                                                  "consistency.png"}


def test_eval_profile_needs_scans(tmp_path):
    traj = tmp_path / "t.txt"
    write_trajectory(Trajectory(se3.identity(3), np.arange(3.0)), traj, "tum")
    result = run("eval", "--gt", str(traj), "--est", str(traj), "--profile", str(tmp_path / "p"))
    assert result.exit_code == 2 and "--scans" in result.output
