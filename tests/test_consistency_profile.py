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
from dm2_backend.evaluation import plots, profile_cells
from dm2_backend.evaluation import profile_stretches as stretches
from dm2_backend.evaluation.consistency_profile import GAP, consistency_profile, write_profiles
from dm2_backend.formats import ReadOptions, write_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.pipeline.inputs import load_inputs
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
    assert np.isfinite(p.score).all()
    assert p.levels_m["all"] < 0.03  # 2 cm range noise: the frames agree at the sensor's noise


@pytest.mark.parametrize("break_it", ["one frame", "jump", "drift"])
def test_a_broken_stretch_of_the_street_is_flagged_and_nothing_far_from_it(break_it):
    _, seq, gt = street()
    poses = {"one frame": lambda: one_frame(gt, 40), "jump": lambda: jump_from(gt, 40),
             "drift": lambda: drifting(gt, 40, 10)}[break_it]()
    p = profile(seq, poses)
    hit, false = flags(p, gt, poses)
    assert hit and false == 0, (p.segments, false)


@pytest.mark.parametrize("one_pass", [True, False])
@pytest.mark.parametrize("poses_of", ["truth", "jump"])
def test_a_sequence_longer_than_the_cell_budget_is_judged_a_stretch_at_a_time(monkeypatch, poses_of, one_pass):
    """A budget of 8 frames' cells for 80 frames (as 1.5 million cells for 1,000 frames): the frames are
    judged a stretch at a time, each at full density, whether all cells fit in memory at once (a slice of them a
    stretch) or not (summed 40 frames at a time into a temporary file the stretches slice: as 20,000 frames), so
    the truth scores as in one piece (no flag, each view's median within 15 %) and a jump is still found, nothing
    far from it."""
    _, seq, gt = street()
    full = profile(seq, gt)
    monkeypatch.setattr(stretches, "MAX_CELLS", 8 * profile_cells.CELLS_PER_FRAME)
    one_pass_cells = profile_cells.ONE_PASS_CELLS if one_pass else 40 * profile_cells.CELLS_PER_FRAME
    monkeypatch.setattr(profile_cells, "ONE_PASS_CELLS", one_pass_cells)
    poses = gt if poses_of == "truth" else jump_from(gt, 40)
    p = profile(seq, poses)
    assert np.isfinite(p.score).all()
    if poses_of == "truth":
        assert p.segments == [], p.segments
        for view in ("all", "past", "future"):
            assert np.nanmedian(p.views_m[view]) == pytest.approx(np.nanmedian(full.views_m[view]), rel=0.15), view
    else:
        hit, false = flags(p, gt, poses)
        assert hit and false == 0, (p.segments, false)


def test_the_sets_of_poses_judged_side_by_side_score_as_one_after_the_other(monkeypatch):
    """Two sets of poses on two threads score exactly as on one thread, one set after the other: the stretches
    (8 frames' cells a set) do not depend on the processors."""
    _, seq, gt = street()
    candidates = {"truth": gt, "jump": jump_from(gt, 40)}
    monkeypatch.setattr(stretches, "MAX_CELLS", 16 * profile_cells.CELLS_PER_FRAME)
    monkeypatch.setattr(stretches, "WORKERS", 2)
    side_by_side = cp.consistency_profiles(seq, candidates, seq.timestamps)
    monkeypatch.setattr(stretches, "WORKERS", 1)
    in_turn = cp.consistency_profiles(seq, candidates, seq.timestamps)
    for name in candidates:
        for view in ("all", "past", "future"):
            np.testing.assert_array_equal(side_by_side[name].views_m[view], in_turn[name].views_m[view])
        assert side_by_side[name].noise_m == in_turn[name].noise_m


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
    assert np.allclose(doc["broken"]["score"], profiles["broken"].score)
    assert doc["broken"]["segments"][0]["first"] <= 40 <= doc["broken"]["segments"][0]["last"]
    rows = list(csv.DictReader((tmp_path / "consistency.csv").open()))
    assert len(rows) == len(gt)
    assert [int(r["broken_flagged"]) for r in rows] == profiles["broken"].flagged.astype(int).tolist()
    assert float(rows[40]["stamp_s"]) == pytest.approx(4.0)
    assert [i for i, r in enumerate(rows) if r["step_held"] == "1"] == [39, 40]
    assert not any(r["step_contradicted"] == "1" for r in rows)
    fig = plots.consistency_figure(gt[:, :3, 3], profiles)
    top = next(ax for ax in fig.axes if ax.get_title().startswith("broken:"))  # one map panel per profile
    series = next(ax for ax in fig.axes if ax.get_xlabel() == "frame")
    assert np.allclose(top.collections[0].get_offsets(), gt[:, :2, 3])  # x-y top view of the given positions
    assert np.allclose(top.collections[0].get_array(), profiles["broken"].score)
    lines = [ln for ln in series.get_lines() if len(ln.get_xdata()) == len(gt)]
    assert np.allclose(lines[-1].get_ydata(), profiles["broken"].score)
    assert series.get_xlim() == (-0.5, len(gt) - 0.5) and series.get_ylim()[0] == 0.0
    assert series.get_ylim()[1] >= max(np.nanmax(profiles["broken"].score), 1.0)  # the threshold (1) in sight
    assert float(rows[40]["broken_past_m"]) == pytest.approx(profiles["broken"].views_m["past"][40], rel=1e-5)


def test_eval_writes_the_profile_and_names_the_flagged_frames(tmp_path):
    scans, _, gt = street()
    write_sequence(tmp_path / "seq", scans, gt, one_frame(gt, 40), 10.0)
    result = run("eval", "--scans", str(tmp_path / "seq" / "velodyne"), "--est", str(tmp_path / "seq" / "poses.txt"),
                 "--est", str(tmp_path / "seq" / "warm_start.txt"), "--est-times", str(tmp_path / "seq" / "times.txt"),
                 "--profile", str(tmp_path / "profile"))
    assert result.exit_code == 0, result.output
    lines = [ln for ln in result.output.splitlines() if ln.startswith("consistency:")]
    assert "poses: " in lines[0] and lines[0].endswith("no flagged frame")
    assert "warm_start: " in lines[1] and "1 flagged stretch" in lines[1] and " at 40" in lines[1], lines
    assert {p.name for p in (tmp_path / "profile").iterdir()} == {"consistency.json", "consistency.csv",
                                                                  "consistency.png"}


def test_eval_profile_needs_scans(tmp_path):
    traj = tmp_path / "t.txt"
    write_trajectory(Trajectory(se3.identity(3), np.arange(3.0)), traj, "tum")
    result = run("eval", "--gt", str(traj), "--est", str(traj), "--profile", str(tmp_path / "p"))
    assert result.exit_code == 2 and "--scans" in result.output


def test_a_trajectory_refined_to_the_noise_floor_raises_no_flag():
    """1 mm and 0.01 degree of error on every frame of the street (a refine at the sensor's floor): nothing a
    user should look at."""
    _, seq, gt = street()
    rng = np.random.default_rng(0)
    near = gt.copy()
    near[:, :3, 3] += rng.normal(0.0, 1e-3, (len(gt), 3))
    near[:, :3, :3] = near[:, :3, :3] @ se3.exp_so3(rng.normal(0.0, np.radians(0.01), (len(gt), 3)))
    assert profile(seq, near).segments == []


def test_the_fast_street_of_dm2_simulate_raises_no_flag_from_truth_or_the_floor_and_a_jump_does():
    """``dm2 simulate --frames 120`` (the README's street: 2.9 m a frame, so two-frame stretches that see a fifth
    of each frame): a flat cell measured against another surface's plane reaching into its voxel (the ground into
    a wall's cell) and a score from a subset of the cells flagged its true poses in 6 stretches."""
    scans, gt, _ = simulate(SimSettings(frames=120), progress=False)
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), timestamps=np.arange(len(scans)) * 0.1, planar=False)
    rng = np.random.default_rng(1)
    near = gt.copy()
    near[:, :3, 3] += rng.normal(0.0, 1e-3, (len(gt), 3))
    near[:, :3, :3] = near[:, :3, :3] @ se3.exp_so3(rng.normal(0.0, np.radians(0.01), (len(gt), 3)))
    jumped = jump_from(gt, 60)
    profiles = cp.consistency_profiles(seq, {"truth": gt, "floor": near, "jump": jumped}, seq.timestamps)
    assert profiles["truth"].window == 2
    assert profiles["truth"].segments == [] and profiles["floor"].segments == []
    hit, false = flags(profiles["jump"], gt, jumped)
    assert hit and false == 0, profiles["jump"].segments


def test_the_flag_threshold_stands_out_from_the_frames_and_never_falls_below_its_floor():
    """``SPREAD`` robust standard deviations above the view's median, and at least the floor (the noise the
    planes measure): a trajectory whose frames all agree to a hair is not flagged for its scene's own spread."""
    distance = np.array([1.0, 2.0, 3.0, 4.0, 5.0, np.nan]) * 1e-3
    level, threshold = cp.threshold_of(distance)
    assert level == pytest.approx(3e-3) and threshold == pytest.approx(3e-3 + cp.SPREAD * 1.4826e-3)
    assert cp.threshold_of(distance, floor=0.1)[1] == pytest.approx(0.1)
    assert cp.threshold_of(np.full(4, np.nan)) == (pytest.approx(np.nan, nan_ok=True), np.inf)


def test_each_view_is_judged_against_its_own_level():
    """A frame's flat cells against its neighbours' dense planes agree several times closer than its points against
    the map of all others. A frame only the neighbour views see off (the long street's jump: five times their level,
    under the "all" view's) is flagged by its view; judged by the largest view's level, it was not."""
    rng = np.random.default_rng(0)
    n = 200
    views = {"all": 0.010 + 0.001 * rng.random(n), "past": 0.002 + 0.0002 * rng.random(n),
             "future": 0.002 + 0.0002 * rng.random(n)}
    views["past"][100] = 0.009
    assert views["past"][100] < views["all"].min()
    p = cp._profile(views, 0.001, None, 1.0, 4)
    assert [(s.first, s.last, s.peak_frame, s.peak_view) for s in p.segments] == [(100, 100, 100, "past")]
    assert p.score[100] == pytest.approx(0.009 / p.thresholds_m["past"]) and p.score[100] > 1.0
    assert np.nanmax(np.delete(p.score, 100)) < 1.0


def _planar_street(frames: int) -> tuple[ScanSequence, np.ndarray]:
    """The benchmark's planar simulation (0.5 m between frames)."""
    scans, gt, _ = simulate(SimSettings(frames=frames, seed=0, extent=28.4, laps=2.0, planar=True), progress=False)
    return ScanSequence(lambda i: Scan(scans[i]), len(scans), planar=True), gt


def test_the_true_poses_of_a_planar_simulation_raise_no_flag_and_a_jump_does():
    seq, gt = _planar_street(500)
    p = consistency_profile(seq, gt, planar=True)
    assert p.segments == [], p.segments
    broken = jump_from(gt, 250)
    hit, false = flags(consistency_profile(seq, broken, planar=True), gt, broken)
    assert hit and false == 0


def test_noise_free_scans_are_not_flagged_below_their_resolution(tmp_path):
    """The DeepMapping 2D set is noise free: its planes measure the float rounding of the coordinates (about
    1e-5 of its units), and under the former rule (1.75 times the lower quartile) the true poses were flagged on a
    third of the frames. The noise is taken as at least a hundredth of the point spacing."""
    import tarfile

    import scipy.io

    from dm2_backend.formats.scan_folder import read_scan_file

    tar = DATA / "deepmapping2d" / "v1_pose0.tar"
    need(tar)
    with tarfile.open(tar) as tf:
        tf.extractall(tmp_path, filter="data")
    src = tmp_path / "v1_pose0"
    points = []
    for f in sorted(src.glob("*.pcd"), key=lambda f: int(f.stem)):
        pts = read_scan_file(f).points
        points.append((pts[np.any(pts != 0, axis=1)] * 512).astype(np.float32))  # as DeepMapping's eval_2D.py
    gt = se3.from_xy_yaw(scipy.io.loadmat(src / "gt_pose.mat")["pose"])
    seq = ScanSequence(lambda i: Scan(points[i]), len(points), planar=True)
    p = consistency_profile(seq, gt, planar=True)
    # the resolution floor sets the threshold of the "all" view
    assert p.levels_m["all"] < 1e-4 and p.thresholds_m["all"] > 100 * p.levels_m["all"]
    assert p.segments == [], p.segments


def test_the_true_poses_of_a_simulated_depth_camera_raise_no_flag(tmp_path):
    from dm2_backend.simulate.depth_room import write_depth_room

    write_depth_room(tmp_path / "room", 40, "walk", progress=False)
    inputs = load_inputs(tmp_path / "room", None, tmp_path / "room" / "truth.tum", None, ReadOptions())
    p = consistency_profile(inputs.scans, inputs.given.poses)
    assert p.segments == [], p.segments
    assert p.thresholds_m["all"] >= cp.FLOOR * p.noise_m


def test_a_frames_own_cells_in_the_map_do_not_judge_it():
    """Leave-one-out on a sampled map: a frame scores against a map that holds its own sampled cells as against
    the map of the other frames alone (where it has no pair), within what its cells change of which voxels are
    flat (a voxel two frames see)."""
    from dm2_backend.evaluation.profile_map import SparseMap, judged_against_map
    from dm2_backend.evaluation.profile_stretches import _sampled
    from dm2_backend.evaluation.profile_views import CAP, root
    from dm2_backend.kernel.planes import Cells

    _, seq, gt = street()
    voxel = cp.profile_voxel(seq)
    cells = profile_cells.cells_of(seq, voxel, 10**9, 0, False, False)
    sampled = _sampled(cells, 256, np.searchsorted(cells.frame, np.arange(len(gt) + 1)), 0)
    judged = np.zeros(len(gt), bool)
    judged[[10, 40, 70]] = True
    others = ~judged[sampled.frame]
    without = Cells(*(getattr(sampled, f)[others] for f in ("frame", "count", "mean", "scatter")), sampled.size)
    with_own = root(judged_against_map(cells, gt, judged, SparseMap.of(sampled, gt, voxel), CAP))
    alone = root(judged_against_map(cells, gt, judged, SparseMap.of(without, gt, voxel), CAP))
    assert np.isfinite(with_own[judged]).all()
    np.testing.assert_allclose(with_own[judged], alone[judged], rtol=0.25)


def test_the_console_line_counts_the_stretches_and_names_the_worst_few():
    segments = [{"first": 10 * i, "last": 10 * i + 2, "start_s": None, "end_s": None, "peak_frame": 10 * i + 1,
                 "peak": 1.0 + i, "peak_view": "past"} for i in range(6)]
    text = cp.flag_text({"levels_m": {"all": 0.01, "past": 0.002}, "thresholds_m": {"all": 0.02, "past": 0.004},
                         "segments": segments, "flagged_frames": 18})
    assert text.startswith("frames agree to 0.01 m (all), 0.002 m (past), flagged above 0.02 m (all), 0.004 m (past): ")
    assert "6 flagged stretches (18 frames)" in text
    assert "50-52 peak 6x the past view's threshold at 51" in text and "0-2" not in text  # the worst first
    assert text.count(" peak ") == cp.NAMED and "the other 3 in consistency.csv" in text


@pytest.mark.parametrize("where", ["near the origin", "at UTM coordinates", "two frames 10,000 km away"])
def test_a_frame_judged_against_the_map_of_every_frame_scores_as_that_maps_own_leave_one_out(where):
    """The "all" view of a long sequence judges a frame's cells against the map every frame makes
    (``profile_map``): where that map holds every frame's cells as judged, a frame scores as the map's own
    leave-one-out (``kernel.planes.disagreement``), on true and jumped poses, wherever the poses lie (a map wider
    than a packed voxel key spans is matched by grouping the keys)."""
    from dm2_backend.evaluation.profile_map import SparseMap, judged_against_map
    from dm2_backend.evaluation.profile_views import CAP, root
    from dm2_backend.kernel.planes import assign, disagreement

    _, seq, gt = street()
    voxel = cp.profile_voxel(seq)
    cells = profile_cells.cells_of(seq, voxel, 10**9, 0, False, False)
    judged = np.ones(len(gt), bool)
    for poses in (gt, jump_from(gt, 40)):
        poses = poses.copy()
        if where == "at UTM coordinates":
            poses[:, :3, 3] += [5.4e5, 5.3e6, 300.0]
        if where.startswith("two frames"):  # they share planes there: the map spans more than a packed key
            poses[70:72, :3, 3] += [1e7, 0.0, 0.0]
        world_map = SparseMap.of(cells, poses, voxel)
        assert any(level.low is None for level in world_map.levels) == where.startswith("two frames")
        own = root(disagreement(assign(cells, poses, voxel), poses, CAP, bounded=True))
        got = root(judged_against_map(cells, poses, judged, world_map, CAP))
        assert np.array_equal(np.isfinite(got), np.isfinite(own)) and np.isfinite(got[judged]).all()
        ratio = got[judged] / own[judged]
        assert np.median(ratio) == pytest.approx(1.0, abs=0.02) and np.all(np.abs(ratio - 1.0) < 0.2), ratio
