"""The DeepMapping2 training loop: it lowers the error of a drifting warm start, the ablation switches run,
runs are deterministic under a seed, resuming from a checkpoint equals an uninterrupted run, and a
non-finite loss stops the run with the best poses kept."""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np
import pytest
import torch
from optim_cases import Case, frames_of, one_thread, planar_case, small_config

from dm2_backend.config.optimiser import OptimConfig, switch
from dm2_backend.kernel.geometry import se3, se3_torch
from dm2_backend.kernel.prepared import ScanScale
from dm2_backend.optim import losses
from dm2_backend.optim.batching import make_groups, random_groups, temporal_groups
from dm2_backend.optim.checkpoint import CHECKPOINT
from dm2_backend.optim.derived import LossRegime, PoseRegime, derive, loss_regime, pose_regime, sampled_points
from dm2_backend.optim.epoch import Epoch
from dm2_backend.optim.problem import Execution, Problem, Watch
from dm2_backend.optim.regime import disagreement, locally_accurate
from dm2_backend.optim.stop import StopReason
from dm2_backend.optim.trainer import Optimiser, OptimResult
from dm2_backend.pipeline.live import ate_rmse
from dm2_backend.plugins.topology_radius import RadiusTopology
from dm2_backend.simulate.lidar import LidarModel
from dm2_backend.simulate.sequence import SimSettings, simulate

#: the optimiser on the CPU without a progress bar
CPU = Execution(device="cpu", progress=False)


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


EPOCHS = 4


@pytest.fixture(scope="module")
def case() -> Case:
    return planar_case()


def optimiser(case: Case, seed: int = 0, metric=None, pairwise=None, **cfg) -> Optimiser:
    return Optimiser(Problem(case.frames, case.topology, pairwise or case.pairwise, case.warm),
                     small_config(**{"epochs": EPOCHS, **cfg}), Execution(seed, "cpu", progress=False),
                     Watch(metric=metric))


class Recorder:
    """Metric callback: ATE against the ground truth, keeping every epoch's poses; raises
    KeyboardInterrupt (like Ctrl-C) when called for epoch ``interrupt_at``."""

    def __init__(self, gt: np.ndarray, interrupt_at: int | None = None) -> None:
        self.gt, self.interrupt_at, self.poses = gt, interrupt_at, []

    def __call__(self, poses: np.ndarray) -> float:
        if self.interrupt_at is not None and len(self.poses) == self.interrupt_at:
            raise KeyboardInterrupt
        self.poses.append(poses.copy())
        return ate_rmse(self.gt, poses)


def strip_times(history: tuple[Epoch, ...]) -> list[Epoch]:
    return [replace(row, seconds=0.0) for row in history]


@pytest.fixture(scope="module")
def full_run(case, tmp_path_factory) -> tuple[OptimResult, Recorder, object]:
    """An uninterrupted run with checkpoints (``resume`` on an empty folder starts from scratch)."""
    folder = tmp_path_factory.mktemp("full")
    rec = Recorder(case.gt)
    return optimiser(case, metric=rec).run(checkpoint_dir=folder, resume=True), rec, folder


def test_refine_lowers_ate_with_icp_pairwise(case, full_run):
    result, rec, folder = full_run
    before, after = ate_rmse(case.gt, case.warm), ate_rmse(case.gt, result.poses)
    assert after <= 0.7 * before, (before, after)
    assert len(result.history) == EPOCHS and result.stopped.reason is StopReason.BUDGET
    assert [row.epoch for row in result.history] == list(range(EPOCHS))
    assert all(None not in (row.bce, row.chamfer, row.consistency, row.ate) for row in result.history)
    assert result.history[-1].ate == pytest.approx(ate_rmse(case.gt, rec.poses[-1]))
    assert result.best_epoch == int(np.argmin([row.loss for row in result.history]))
    np.testing.assert_array_equal(result.poses, rec.poses[result.best_epoch])
    np.testing.assert_allclose(result.poses[0], case.warm[0], atol=1e-9)  # the gauge: frame 0 stays put
    assert (folder / CHECKPOINT).is_file()
    assert set(asdict(result.derived)) == {"unit", "finest_cell", "free_margin", "chamfer_truncate",
                                   "step_translation", "step_rotation", "epochs", "first_order", "drift", "lr_pose",
                                   "start_disagreement", "locally_accurate_start", "use_bce", "use_consistency",
                                   "chamfer_metric", "pose_warmup", "pose_warmup_steps", "polish",
                                   "points_per_frame", "max_disagreement"}
    assert result.selection == f"lowest epoch loss: epoch {result.best_epoch}"  # no map metric given
    assert result.derived.epochs == EPOCHS
    # a drifting warm start (not loop-closed, registrations disagree with it): drift terms, full pose steps
    assert result.derived.start_disagreement > OptimConfig().accurate_below * result.derived.unit
    assert result.derived.locally_accurate_start is False
    assert result.derived.drift is True and result.derived.lr_pose == 1.0


def test_refine_lowers_ate_with_ground_truth_pairwise(case):
    result = optimiser(case, pairwise=case.pairwise_from(case.gt)).run()
    assert ate_rmse(case.gt, result.poses) <= 0.7 * ate_rmse(case.gt, case.warm)


@pytest.mark.parametrize("switches,absent", [
    ({"use_consistency": False}, "consistency"),
    ({"use_bce": False}, "bce"),
    ({"use_chamfer": False}, "chamfer"),
    ({"batching": "temporal"}, None),
    ({"batching": "random"}, None),
    ({"pose_model": "lnet"}, None),
    ({"drift": False}, None),
], ids=["no-consistency", "no-bce", "no-chamfer", "temporal", "random", "lnet", "no-drift"])
def test_ablation_switches_run(case, switches, absent):
    result = optimiser(case, epochs=2, **switches).run()
    assert len(result.history) == 2 and result.stopped.reason is StopReason.BUDGET
    assert np.isfinite(result.poses).all() and result.poses.shape == case.warm.shape
    # every variant still does the job in two epochs: measured 0.30-0.67 of the warm start's error against the
    # truth (no drift terms 0.67, the full objective 0.30)
    assert ate_rmse(case.gt, result.poses) < 0.8 * ate_rmse(case.gt, case.warm)
    for row in result.history:
        assert np.isfinite(row.loss)
        if absent is not None:
            assert getattr(row, absent) is None


def test_unknown_choices_are_errors(case):
    with pytest.raises(ValueError, match="batching"):
        optimiser(case, batching="spatial")
    with pytest.raises(ValueError, match="pose_model"):
        optimiser(case, pose_model="mlp")
    with pytest.raises(ValueError, match="bogus"):
        OptimConfig.model_validate({"epochs": 2, "bogus": 1})
    with pytest.raises(ValueError, match="frozen"):  # validated once: never changed afterwards
        OptimConfig().epochs = 3  # type: ignore[misc]


def test_deterministic_under_a_seed(case, full_run):
    result = optimiser(case, metric=Recorder(case.gt)).run()
    np.testing.assert_array_equal(result.poses, full_run[0].poses)
    assert strip_times(result.history) == strip_times(full_run[0].history)
    other = optimiser(case, seed=1, epochs=1).run()
    same = optimiser(case, seed=0, epochs=1).run()
    assert np.abs(other.poses - same.poses).max() > 1e-6


def test_resume_equals_uninterrupted(case, full_run, tmp_path):
    full, _, _ = full_run
    interrupted = Recorder(case.gt, interrupt_at=EPOCHS // 2)
    with pytest.raises(KeyboardInterrupt):
        optimiser(case, metric=interrupted).run(checkpoint_dir=tmp_path)
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert state["epoch"] == EPOCHS // 2 - 1 and len(state["history"]) == EPOCHS // 2
    rec = Recorder(case.gt)
    resumed = optimiser(case, metric=rec).run(checkpoint_dir=tmp_path, resume=True)
    assert len(rec.poses) == EPOCHS - EPOCHS // 2  # only the remaining epochs ran
    np.testing.assert_array_equal(resumed.poses, full.poses)
    np.testing.assert_array_equal(rec.poses[-1], full_run[1].poses[-1])
    assert resumed.best_epoch == full.best_epoch
    assert strip_times(resumed.history) == strip_times(full.history)
    # resuming a finished run returns its result without training
    again = optimiser(case, metric=rec).run(checkpoint_dir=tmp_path, resume=True)
    np.testing.assert_array_equal(again.poses, full.poses)
    assert len(rec.poses) == EPOCHS - EPOCHS // 2


def test_resume_extends_a_finished_shorter_run(case, tmp_path):
    """A finished E/2-epoch run resumed with E epochs continues at epoch E/2 (more epochs later)."""
    optimiser(case, epochs=EPOCHS // 2).run(checkpoint_dir=tmp_path)
    rec = Recorder(case.gt)
    result = optimiser(case, metric=rec).run(checkpoint_dir=tmp_path, resume=True)
    assert len(rec.poses) == EPOCHS - EPOCHS // 2
    assert [row.epoch for row in result.history] == list(range(EPOCHS))


@pytest.mark.parametrize("nan_at_step", [0, 9])
def test_non_finite_loss_stops_and_keeps_best(case, monkeypatch, nan_at_step):
    calls = []
    real = losses.occupancy_bce

    def bce(field, occupied, free):
        calls.append(1)
        value = real(field, occupied, free)
        return value * float("nan") if len(calls) == nan_at_step + 1 else value

    monkeypatch.setattr(losses, "occupancy_bce", bce)
    rec = Recorder(case.gt)
    opt = optimiser(case, metric=rec)
    result = opt.run()
    epoch, step = divmod(nan_at_step, opt.steps_per_epoch)
    assert result.stopped.reason is StopReason.NON_FINITE and f"epoch {epoch} step {step}" in result.stopped.detail
    assert len(result.history) == epoch and np.isfinite(result.poses).all()
    if epoch == 0:
        assert result.best_epoch == -1
        np.testing.assert_allclose(result.poses, case.warm, atol=1e-9)
    else:
        assert result.best_epoch == int(np.argmin([row.loss for row in result.history]))
        np.testing.assert_array_equal(result.poses, rec.poses[result.best_epoch])


# ---------------------------------------------------------------- batching and derived lengths
def test_batching_groups():
    t = temporal_groups(6, 2)
    np.testing.assert_array_equal(t[0], [-1, 1])
    np.testing.assert_array_equal(t[3], [2, 4])
    np.testing.assert_array_equal(temporal_groups(6, 4)[5], [4, -1, 3, -1])
    r = random_groups(50, 5, np.random.default_rng(0))
    assert r.shape == (50, 5) and (r >= 0).all() and (r < 50).all()
    assert not (r == np.arange(50)[:, None]).any()  # never the anchor itself
    topo = np.arange(12).reshape(4, 3) % 4
    assert make_groups("topology", topo, 0) is topo
    np.testing.assert_array_equal(make_groups("random", topo, 3), make_groups("random", topo, 3))
    with pytest.raises(ValueError):
        make_groups("spatial", topo, 0)


def test_derived_lengths_follow_the_data():
    d = derive(OptimConfig(), ScanScale(spacing=0.2, voxel=0.0, range_median=10.0))
    assert d.unit == pytest.approx(0.4) and d.finest_cell == d.free_margin == d.unit
    assert d.chamfer_truncate == pytest.approx(4.0) and d.step_translation == pytest.approx(0.04)
    assert d.step_rotation == pytest.approx(0.004)
    d = derive(OptimConfig(unit=1.0, step_rotation=0.5), ScanScale(spacing=0.2, voxel=0.5))
    assert d.unit == 1.0 and d.step_rotation == 0.5 and d.step_translation == pytest.approx(0.1)
    assert derive(OptimConfig(), ScanScale(spacing=0.1, voxel=0.3)).unit == pytest.approx(0.6)


def test_pose_regime_follows_start_accuracy():
    drifting, closed = pose_regime(OptimConfig(), False), pose_regime(OptimConfig(), True)
    assert drifting == PoseRegime(drift=True, lr_pose=1.0)
    assert closed == PoseRegime(drift=False, lr_pose=0.05)
    assert pose_regime(OptimConfig(drift=True, lr_pose=0.3), True) == PoseRegime(drift=True, lr_pose=0.3)
    # the measured disagreement: zero where the registrations equal the poses' relative poses
    poses = se3.from_xy_yaw(np.column_stack([np.arange(4.0), np.zeros(4), 0.1 * np.arange(4)]))
    groups = np.array([[1], [2], [3], [-1]])
    rel = np.tile(np.eye(4), (4, 1, 1, 1))
    rel[:3, 0] = se3.relative(poses[:3], poses[1:])
    valid = groups >= 0
    assert disagreement(poses, groups, rel, valid, 10.0) == pytest.approx(0.0, abs=1e-9)
    rel[:3, 0, 0, 3] += 0.2  # every registration 0.2 m off
    assert disagreement(poses, groups, rel, valid, 10.0) == pytest.approx(0.2)
    assert disagreement(poses, groups, rel, np.zeros_like(valid), 10.0) is None
    assert locally_accurate(0.05, 0.4, 0.25) and not locally_accurate(0.2, 0.4, 0.25)
    assert not locally_accurate(None, 0.4, 0.25)


def lidar_case(frames: int, start_at_gt: bool = False) -> Case:
    """A short simulated 16-beam LiDAR sequence; radius topology on the start (the warm start or the ground
    truth) and exact pairwise relatives from the ground truth."""
    lidar = LidarModel(beams=16, columns=360, max_range=40.0)
    scans, gt, warm = simulate(SimSettings(frames=frames, planar=False, extent=20.0, lidar=lidar), progress=False)
    start = gt if start_at_gt else warm
    fr = frames_of(scans, planar=False)
    topo = RadiusTopology().run(fr, start)
    shell = Case(scans, gt, start, fr, topo, None)
    return Case(scans, gt, start, fr, topo, shell.pairwise_from(gt))


def test_3d_sequence_runs():
    """A short 3D LiDAR sequence: 3D occupancy grid, all six pose dimensions free."""
    c = lidar_case(16)
    warm = c.warm
    opt = Optimiser(Problem(c.frames, c.topology, c.pairwise, warm), small_config(epochs=1), CPU)
    assert opt.field.dim == 3 and not opt.planar
    result = opt.run()
    assert np.isfinite(result.poses).all() and not result.stopped.failed
    assert np.abs(result.poses[:, 2, 3] - warm[:, 2, 3]).max() > 0  # z is free in 3D
    # one epoch from a drifting start towards the truth (measured 0.309 -> 0.216 m)
    assert ate_rmse(c.gt, result.poses) < 0.85 * ate_rmse(c.gt, warm)


class MapScores:
    """Map metric returning given values in call order (the first call scores the start), keeping the poses."""

    def __init__(self, values: list[float]) -> None:
        self.values, self.poses = list(values), []

    def __call__(self, poses: np.ndarray) -> float:
        self.poses.append(poses.copy())
        return self.values[len(self.poses) - 1]


def test_select_by_map_returns_the_sharpest_epoch(case):
    scores = MapScores([5.0, 4.0, 2.0, 3.0, 6.0])  # start, epochs 0..3
    opt = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm), small_config(epochs=4),
                    CPU, Watch(map_metric=scores))
    result = opt.run()
    assert result.best_epoch == 1
    np.testing.assert_array_equal(result.poses, scores.poses[2])
    assert [row.map_entropy for row in result.history] == [4.0, 2.0, 3.0, 6.0]
    assert result.selection.startswith("sharpest map: epoch 1")


def test_select_by_map_never_returns_a_blurrier_map_than_the_start(case):
    scores = MapScores([1.0, 2.0, 3.0])
    opt = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm), small_config(epochs=2),
                    CPU, Watch(map_metric=scores))
    result = opt.run()
    assert result.best_epoch == -1 and result.selection.startswith("the start")
    np.testing.assert_allclose(result.poses, case.warm, atol=1e-9)
    # with select "loss" the map metric is only recorded
    loss_run = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm),
                         small_config(epochs=2, select="loss"), CPU,
                         Watch(map_metric=MapScores([1.0, 2.0, 3.0]))).run()
    assert loss_run.best_epoch >= 0 and loss_run.history[0].map_entropy is not None


def test_loss_regime_from_the_pose_graph_start():
    cfg = OptimConfig()
    graph3d = loss_regime(cfg, planar=False, polish=True)
    assert graph3d == LossRegime(use_bce=False, use_consistency=False, chamfer_metric="plane", pose_warmup=1.0)
    assert loss_regime(cfg, planar=True, polish=False) == LossRegime(
        use_bce=True, use_consistency=True, chamfer_metric="point", pose_warmup=0.0)
    explicit = OptimConfig(use_bce=True, use_consistency=True, chamfer_metric="point", pose_warmup=0.5)
    assert loss_regime(explicit, planar=False, polish=True) == LossRegime(
        use_bce=True, use_consistency=True, chamfer_metric="point", pose_warmup=0.5)
    assert sampled_points(cfg, 1024, planar=False) == 512 and sampled_points(cfg, 1024, planar=True) == 256
    assert sampled_points(cfg, 300, planar=False) == 300
    assert sampled_points(OptimConfig(start="prepared"), 1024, planar=False) == 256
    # 3D: the unit follows the raw scans' spacing (the frames are a subsample), planar data the frames'
    scale = ScanScale(spacing=0.4, spacing_raw=0.15, voxel=0.1, range_median=8.0)
    assert derive(cfg, scale, planar=False).unit == pytest.approx(0.3)
    assert derive(cfg, scale, planar=True).unit == pytest.approx(0.8)
    assert derive(cfg, scale, planar=False).chamfer_truncate == pytest.approx(3.0)


def test_plane_chamfer_is_lowest_at_ground_truth():
    c = lidar_case(12, start_at_gt=True)
    gt = c.gt
    opt = Optimiser(Problem(c.frames, c.topology, c.pairwise, gt),
                    small_config(chamfer_metric="plane", points_per_frame=256), CPU)
    assert opt.normals is not None
    # a locally accurate 3D start is polished: Chamfer along the normals only, truncated at one unit
    d = opt.derived
    assert d.polish and not d.use_bce and not d.use_consistency and d.pose_warmup == 1.0
    assert d.chamfer_truncate == d.unit
    np.testing.assert_allclose(np.linalg.norm(opt.normals.numpy(), axis=-1), 1.0, atol=1e-5)

    def chamfer(poses):
        T = torch.from_numpy(poses)
        idx = np.arange(opt.n)
        world = se3_torch.transform(T.float(), opt.points)
        return float(opt._chamfer(idx, opt.groups, idx, T, world, torch.from_numpy(idx)))

    rng = np.random.default_rng(0)
    previous = chamfer(gt)
    for sigma in (0.05, 0.2, 0.5):
        noise = np.concatenate([rng.normal(0, sigma, (len(gt), 3)), rng.normal(0, sigma / 20, (len(gt), 3))], 1)
        noise[0] = 0
        value = chamfer(gt @ se3.from_xyz_euler(noise))
        assert value > previous
        previous = value


@pytest.mark.parametrize("select", ["loss", "map"])
def test_a_diverging_run_returns_its_start_not_a_scattered_map(case, select):
    """Learning rate 1e6: the poses fly apart without a non-finite loss. Scattered frames no longer overlap, so
    both the loss and a local map metric can look better than the start; the registrations tell."""
    from dm2_backend.evaluation.map_quality import MapSampler, MapSettings

    voxel = case.frames.scale.spacing
    sampler = MapSampler(list(case.frames.points), True, voxel, 3 * voxel, MapSettings()) if select == "map" else None
    opt = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm),
                    small_config(epochs=2, lr_pose=1e6, select=select), CPU,
                    Watch(map_metric=None if sampler is None else sampler.entropy))
    result = opt.run()
    assert all(row.rejected is not None for row in result.history)
    assert min(row.disagreement for row in result.history) > 10 * opt.derived.start_disagreement
    assert result.best_epoch == -1 and result.stopped.reason is StopReason.DIVERGED
    np.testing.assert_allclose(result.poses, case.warm, atol=1e-9)


def test_step_budget_keeps_min_epochs(case):
    """The step cap never leaves fewer than ``min_epochs`` passes (a long sequence's frames each get several
    visits), and never more than ``epochs``."""
    steps = len(case.frames) // 16 + 1  # about one epoch
    assert optimiser(case, epochs=6, max_steps=steps).epochs == 2
    assert optimiser(case, epochs=6, max_steps=steps, min_epochs=3).epochs == 3
    assert optimiser(case, epochs=1, max_steps=steps, min_epochs=3).epochs == 1
    assert optimiser(case, epochs=6, max_steps=0).epochs == 6


def test_converged_run_stops_early_and_traces(case):
    """Under the step budget with the map selection, two epochs in a row that neither lower the loss by more
    than ``converge_tol`` nor make a sharper map stop the run; each epoch row traces loss and accuracy against
    the steps."""
    flat_map = lambda poses: 0.0  # noqa: E731  (never sharper than the start)
    run = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm),
                    small_config(epochs=6, converge_tol=1.0), CPU,
                    Watch(map_metric=flat_map, trace=lambda poses: ate_rmse(case.gt, poses))).run()
    assert [row.epoch for row in run.history] == [0, 1, 2] and run.history[-1].converged is not None
    assert not run.stopped.failed and run.best_epoch == -1  # the start: no epoch made a sharper map
    trace = [p for row in run.history for p in row.trace]
    assert [p.step for p in trace] == sorted({p.step for p in trace}) and all(p.ate is not None for p in trace)
    assert run.history[-1].steps == trace[-1].step
    full = Optimiser(Problem(case.frames, case.topology, case.pairwise, case.warm),
                     small_config(epochs=6, converge_tol=0.0), CPU, Watch(map_metric=flat_map)).run()
    assert len(full.history) == 6 and all(row.converged is None for row in full.history)


def test_chamfer_matches_brute_force_nearest_points(case):
    """The per-frame KD-trees find, for every pair, the same nearest points as comparing all points."""
    opt = optimiser(case)
    T = torch.from_numpy(case.gt @ se3.from_xyz_euler(np.full((len(case.gt), 6), 0.01)))
    idx = np.arange(opt.n)
    world = se3_torch.transform(T.float(), opt.points)
    got = float(opt._chamfer(idx, opt.groups, idx, T, world, torch.from_numpy(idx)))
    cut, total = opt.derived.chamfer_truncate, {0: [], 1: []}
    for a, row in zip(idx, opt.groups, strict=True):
        for j in row:
            if j < 0 or j == a:
                continue
            d = torch.cdist(world[a], world[j])  # (M, M)
            total[0].append(d.min(1).values.clamp(max=cut))
            total[1].append(d.min(0).values.clamp(max=cut))
    want = float(torch.cat(total[0]).mean() + torch.cat(total[1]).mean())
    assert got == pytest.approx(want, rel=1e-5)


@pytest.mark.parametrize("given,read", [(True, "on"), (False, "off"), (None, "auto"), ("off", "off")])
def test_a_switch_reads_yamls_booleans_and_null_as_words(given, read):
    """YAML 1.1 reads ``on``/``off`` as booleans, and older dumped configs say null for auto."""
    assert OptimConfig(use_bce=given).use_bce == read == OptimConfig(first_order=given).first_order


def test_an_auto_switch_is_decided_and_an_explicit_one_holds():
    assert switch("auto", True) and not switch("auto", False) and switch("on", False) and not switch("off", True)
    assert OptimConfig(dense=None).dense is True and OptimConfig().dense is True


def test_after_the_dense_stage_the_epochs_do_not_run_and_say_so(case):
    after_dense = Problem(case.frames, case.topology, case.pairwise, case.warm, after_dense=True)
    result = Optimiser(after_dense, small_config(epochs=2), CPU).run()
    assert result.stopped.reason is StopReason.NOT_RUN and result.history == () and result.best_epoch == -1
    np.testing.assert_array_equal(result.poses, Optimiser(after_dense, small_config(epochs=2), CPU).poses())
