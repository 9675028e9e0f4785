"""The dense multi-frame plane term and its second-order stage: exact cell sums, derivatives that match the
cost, the truth as a fixed point, a drifted start brought to the noise floor, a broken stretch found."""

from __future__ import annotations

import re
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from optim_cases import one_thread
from scipy.sparse import bsr_matrix
from scipy.spatial.transform import Rotation

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.kernel import planes
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.geometry.voxels import group_rows
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.scans import Scan, ScanSequence
from dm2_backend.optim.dense import refine_dense
from dm2_backend.optim.stop import StopReason
from dm2_backend.pipeline.live import ate_rmse
from dm2_backend.runtime.memory import release_mapped
from dm2_backend.simulate.broken import bump, closure_graph, wrong_closure
from dm2_backend.simulate.sequence import SimSettings, simulate

VOXEL = 1.5


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@lru_cache(maxsize=1)
def street() -> tuple[planes.Cells, np.ndarray]:
    """80 frames of the simulated 32-beam LiDAR street (2 cm range noise), as cells, and the true poses."""
    scans, gt, _ = simulate(SimSettings(frames=80, seed=3, extent=10.0, laps=1.5), progress=False)
    seq = ScanSequence(lambda i: Scan(scans[i]), len(scans), planar=False)
    return planes.cells_from_scans(seq, VOXEL / 4, 2048, 10**6), gt


def odometry_graph(gt: np.ndarray, sigma_t: float, sigma_r: float, seed: int = 0) -> tuple[PoseGraph, np.ndarray]:
    """A chain of noisy odometry edges (the information of their noise) and its dead-reckoned poses."""
    rng = np.random.default_rng(seed)
    rel = se3.relative(gt[:-1], gt[1:])
    noisy = rel.copy()
    noisy[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, sigma_r, (len(rel), 3))).as_matrix() @ rel[:, :3, :3]
    noisy[:, :3, 3] += rng.normal(0, sigma_t, (len(rel), 3))
    dead = [gt[0]]
    for T in noisy:
        dead.append(dead[-1] @ T)
    info = np.diag([1 / sigma_t**2] * 3 + [1 / sigma_r**2] * 3)
    n = len(gt)
    graph = PoseGraph(ids=np.arange(n), poses=gt.copy(), edges=np.stack([np.arange(n - 1), np.arange(1, n)], 1),
                      relative=noisy, information=np.repeat(info[None], n - 1, 0), planar=False)
    return graph, np.stack(dead)


def test_cells_hold_the_exact_sums_of_their_points():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-2, 2, (5000, 3))
    count, mean, scatter = planes.compress(pts, 0.5)
    _, inv, k = planes._grouped(pts, 0.5, None)
    assert count.sum() == len(pts) and len(count) == k
    distance = np.linalg.norm(pts, axis=1)
    beam = np.floor(pts / distance[:, None] * (np.median(distance) / 0.5)).astype(int)
    depth = np.floor(distance / 0.5).astype(int)
    runs = {}
    for c in range(k):  # each cell: one beam direction, a run of range bins without a gap
        assert len(np.unique(beam[inv == c], axis=0)) == 1
        bins = np.unique(depth[inv == c])
        assert (np.diff(bins) == 1).all()
        runs.setdefault(tuple(beam[inv == c][0]), []).append((bins[0], bins[-1]))
    for spans in runs.values():  # two cells of one direction: an empty bin between them
        spans.sort()
        assert all(b[0] > a[1] + 1 for a, b in zip(spans, spans[1:], strict=False))
    for c in np.argsort(count)[-3:]:  # the largest cells checked against their points directly
        p = pts[inv == c]
        assert count[c] == len(p)
        np.testing.assert_allclose(mean[c], p.mean(0))
        full = (p - p.mean(0)).T @ (p - p.mean(0))
        np.testing.assert_allclose(scatter[c], full[np.triu_indices(3)], atol=1e-9)


def test_beam_cells_are_those_of_a_sort_by_direction_then_range(monkeypatch):
    """The one-key sort gives the cells of the plain two-key sort (beam direction's bin, then range bin; a new cell
    where the direction changes or a range bin is skipped), with points on every side of the sensor, and so does the
    fallback for keys too wide for one int64."""
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(3000, 3)) * rng.uniform(0.3, 40.0, (3000, 1))
    distance = np.linalg.norm(pts, axis=1)
    unit = pts / distance[:, None]
    size, reference = 0.2, float(np.median(distance))
    _, direction = np.unique(np.floor(unit * (reference / size)).astype(np.int64), axis=0, return_inverse=True)
    depth = np.floor(distance / size).astype(np.int64)
    order = np.lexsort((depth, direction.ravel()))
    d, b = direction.ravel()[order], depth[order]
    new_cell = np.r_[True, (d[1:] != d[:-1]) | (b[1:] - b[:-1] > 1)]
    expected = np.empty(len(pts), np.int64)
    expected[order] = np.cumsum(new_cell) - 1
    inv, k = planes._beam_cells(unit, distance, size, reference)
    assert k == int(new_cell.sum()) and np.array_equal(inv, expected)
    monkeypatch.setattr(planes, "flat_keys", lambda keys: None)
    inv, k = planes._beam_cells(unit, distance, size, reference)
    assert k == int(new_cell.sum()) and np.array_equal(inv, expected)
    assert planes._beam_cells(unit[:0], distance[:0], size, reference)[1] == 0


def test_range_noise_across_a_bin_edge_does_not_split_a_surface():
    """Cells lie along the beams: a wall whose noisy ranges straddle a range bin's edge stays one cell per beam
    direction (a grid cut by the noise splits it into a near and a far half, each mean pulled along the beam),
    while a second wall two bins behind it is a cell of its own."""
    rng = np.random.default_rng(1)
    beams = np.column_stack([rng.uniform(-0.25, 0.25, (4000, 2)), np.ones(4000)])
    beams /= np.linalg.norm(beams, axis=1, keepdims=True)
    wall = 2.0 * beams  # 2.0 m from the sensor: an edge of the 0.1 m range bins
    noisy = wall + beams * rng.normal(0, 0.01, (4000, 1))  # 1 cm along the beams

    def cells(pts: np.ndarray) -> tuple[np.ndarray, int]:
        distance = np.linalg.norm(pts, axis=1)
        return planes._beam_cells(pts / distance[:, None], distance, 0.1, 2.0)

    one, k_one = cells(noisy)
    clean, k_clean = cells(wall)
    assert k_one == k_clean  # the noise adds no cell
    assert len(np.unique(np.column_stack([one, clean]), axis=0)) == k_one  # and moves no point to another
    behind = noisy * (2.3 / 2.0)  # the same beams on a wall 0.3 m further
    two, k_two = cells(np.concatenate([noisy, behind]))
    assert k_two == 2 * k_one and len(set(two[:4000]) & set(two[4000:])) == 0


def test_gradient_and_hessian_match_the_cost():
    cells, gt = street()
    rng = np.random.default_rng(1)
    poses = gt.copy()
    poses[:, :3, 3] += rng.normal(0, 0.02, (len(gt), 3))
    a = planes.assign(cells, poses, VOXEL)
    held = planes.fit(a, poses)
    lin = planes.linearise(a, held, poses)
    cost, H, g = lin.cost, lin.H, lin.g
    frame, eps = 40, 1e-6

    def moved(xi: np.ndarray) -> float:
        """The cost with frame ``frame`` at T Exp([omega, v]) (GTSAM's Pose3 retract, rotation first)."""
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
        step[:3, 3] = xi[3:]
        out = poses.copy()
        out[frame] = poses[frame] @ step
        return planes.linearise(a, held, out).cost

    for k in range(6):
        e = np.zeros(6)
        e[k] = eps
        numeric = (moved(e) - moved(-e)) / (2 * eps)
        assert numeric == pytest.approx(g[frame, k], rel=1e-4)
        curvature = (moved(1e3 * e) - 2 * cost + moved(-1e3 * e)) / (1e3 * eps) ** 2
        assert curvature == pytest.approx(H[frame, k, k], rel=1e-2)
    assert np.all(np.linalg.eigvalsh(H[frame]) > -1e-6)
    # the planes are fitted: the cost does not change to first order when they tilt or shift
    pose_scale = np.abs(g).max()
    assert np.abs(lin.g_plane).max() < 1e-6 * pose_scale
    # the cost with the planes fitted again (GTSAM's half squares) is never above the cost with them held
    assert 0.5 * planes.cost(a, poses) <= cost * (1 + 1e-9)


def test_the_truth_is_a_fixed_point():
    cells, gt = street()
    graph, _ = odometry_graph(gt, 0.01, 0.001)
    result = refine_dense(cells, graph, gt, VOXEL)
    assert ate_rmse(gt, result.poses) < 0.002  # the range noise is 0.02 m
    assert result.history and result.stopped.reason is StopReason.CONVERGED


def test_a_drifted_start_reaches_the_noise_floor():
    cells, gt = street()
    graph, dead = odometry_graph(gt, 0.01, 0.001, seed=2)
    start = ate_rmse(gt, dead)
    floor = ate_rmse(gt, refine_dense(cells, graph, gt, VOXEL).poses)
    result = refine_dense(cells, graph, dead, VOXEL)
    end = ate_rmse(gt, result.poses)
    # a dead-reckoned chain without loop edges (its soft bending modes follow the planes: held planes crept)
    assert start > 0.05 and end < 2 * floor and result.stopped.reason is StopReason.CONVERGED
    assert result.history[-1].sigma < 0.5 * result.history[0].sigma  # the map's noise scale: sharper


def test_a_broken_stretch_disagrees_with_the_others_planes():
    cells, gt = street()
    n = len(gt)
    bent = gt.copy()
    bent[:, 1, 3] += 0.15 * np.clip(1 - np.abs(np.arange(n) - 40) / 6, 0, 1)
    a = planes.assign(cells, gt, VOXEL)
    worst = np.argsort(-np.nan_to_num(planes.disagreement(a, bent)))[:5]
    assert np.all(np.abs(worst - 40) <= 6)
    jump = gt.copy()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 2, degrees=True).as_matrix()
    T[:3, 3] = [0.3, 0, 0]
    jump[n // 2:] = gt[n // 2] @ T @ se3.inverse(gt[n // 2]) @ gt[n // 2:]
    scores = planes.agreement_score(cells, {"truth": gt, "bent": bent, "jump": jump}, VOXEL)
    assert scores["truth"] < min(scores["bent"], scores["jump"])


def test_a_wrong_closure_forced_into_the_graph_is_overruled_by_the_planes():
    """The street's graph (odometry and every pair within 3 m, 1 cm / 1 mrad) with one closure 1 m / 5 deg off,
    weighing ten times the others, bends the path at both ends (what gtsam returns); the dense stage, started
    there with that same graph, straightens it (the graph's Cauchy kernel lets the planes win) and the guard,
    without ground truth, prefers its result."""
    cells, gt = street()
    bent = wrong_closure(gt, 2, 53, bump(1.0, 5.0), radius=3.0)
    graph = closure_graph(gt, 2, 53, bump(1.0, 5.0), radius=3.0, information=np.diag([1e4] * 3 + [1e6] * 3))
    assert ate_rmse(gt, bent) > 0.05
    result = refine_dense(cells, graph, bent, VOXEL)
    assert ate_rmse(gt, result.poses) < 0.002
    scores = planes.agreement_score(cells, {"bent": bent, "dense": result.poses}, VOXEL)
    assert scores["dense"] < scores["bent"]


def test_dense_options_are_checked():
    for bad in ({"dense_rounds": 0}, {"dense_voxel": -1.0}, {"dense_cells_per_frame": 0}, {"dense_max_cells": 0}):
        with pytest.raises(ValueError, match="dense"):
            OptimConfig(**bad)


def _prepared_3d(frames: int = 12):
    """A small 3D preparation (odometry only) for the dense stage's guard."""
    from optim_cases import frames_of

    from dm2_backend.kernel.prepared import Pairwise, Topology
    from dm2_backend.prepare.steps import Prepared

    scans, gt, warm = simulate(SimSettings(frames=frames, seed=5, extent=10.0, laps=0.5), progress=False)
    fr = frames_of(scans, planar=False)
    n = len(scans)
    empty = Pairwise(np.zeros((n, 0, 4, 4)), np.zeros((n, 0), bool), np.zeros((n, 0)), np.zeros((n, 0)))
    seq = ScanSequence(lambda i: Scan(scans[i]), n, planar=False)
    return Prepared(fr, warm, Topology(np.zeros((n, 0), int)), empty), seq, gt


@pytest.mark.parametrize("scores", [{"warm start": 1.0, "graph": 0.5, "dense": 2.0},
                                    {"warm start": np.nan, "graph": np.nan, "dense": np.nan}])
def test_a_dense_result_that_agrees_worse_is_not_kept(monkeypatch, scores):
    from dm2_backend.optim.dense import DenseResult
    from dm2_backend.pipeline import dense_start as start_module

    prep, seq, gt = _prepared_3d()
    given = start_module.Start(gt, start_module.StartKind.GRAPH, "the pose-graph solution")
    moved = gt.copy()
    moved[:, 0, 3] += 0.5
    monkeypatch.setattr(start_module, "refine_dense", lambda *a, **k: DenseResult(moved, [], 0.0))
    monkeypatch.setattr(start_module, "agreement_score", lambda *a, **k: dict(scores))
    out = start_module.dense_start(seq, prep, given, OptimConfig())
    np.testing.assert_array_equal(out.poses, gt)  # the start (graph) agreed best, or nothing could be judged
    assert out.name is start_module.StartKind.GRAPH and not out.refined
    assert out.dense.returned is start_module.Kept.GRAPH


def test_a_warm_start_that_agrees_best_is_named_as_such(monkeypatch):
    """The judge keeps the front end's warm start over both the graph start and the dense result: the start is
    the warm start, by name (never relabelled as the prepared poses)."""
    from dm2_backend.optim.dense import DenseResult
    from dm2_backend.pipeline import dense_start as start_module

    prep, seq, gt = _prepared_3d()
    moved = gt.copy()
    moved[:, 0, 3] += 0.5
    monkeypatch.setattr(start_module, "refine_dense", lambda *a, **k: DenseResult(moved, [], 0.0))
    monkeypatch.setattr(start_module, "agreement_score",
                        lambda *a, **k: {"warm start": 0.1, "graph": 0.5, "dense": 2.0})
    out = start_module.dense_start(seq, prep, start_module.Start(gt, start_module.StartKind.GRAPH, "graph"),
                                   OptimConfig())
    np.testing.assert_array_equal(out.poses, prep.warm_start)
    assert out.name is start_module.StartKind.WARM_START and out.dense.returned is start_module.Kept.WARM_START
    assert out.summary()["name"] == "warm start" and not out.locally_accurate


def test_a_dense_result_that_cuts_the_sequence_is_not_kept(monkeypatch):
    """Its frames agree best with the others' planes, but one of its steps is 2 m and 29 deg from the odometry's:
    the start stands, and the report says why."""
    from dm2_backend.config.schema import PluginSection
    from dm2_backend.optim.dense import DenseResult
    from dm2_backend.pipeline import dense_start as start_module

    prep, seq, gt = _prepared_3d(30)
    # the registration's correspondence distance as configured (0.3 m: a 1.2 m slide, 13 deg at the 5.4 m median
    # range), not the default from these sparse frames' 0.6 m point spacing
    prep = replace(prep, resolved={"registration": PluginSection(name="icp", options={"max_distance": 0.3})})
    cut = gt.copy()
    cut[16:] = se3.make_poses(Rotation.from_rotvec([0, 0, 0.5]).as_matrix(), np.array([5.0, 0, 0])) @ gt[16:]
    monkeypatch.setattr(start_module, "refine_dense", lambda *a, **k: DenseResult(cut, [], 0.0))
    scores = {"warm start": 1.0, "prepared": 0.5, "dense": 0.1}
    monkeypatch.setattr(start_module, "agreement_score", lambda *a, **k: dict(scores))
    given = start_module.Start(prep.warm_start, start_module.StartKind.PREPARED, "the prepared poses")
    out = start_module.dense_start(seq, prep, given, OptimConfig())
    np.testing.assert_array_equal(out.poses, prep.warm_start)
    assert not out.refined and out.dense.returned is start_module.Kept.PREPARED
    assert out.dense.cuts.steps.tolist() == [15]
    assert "cuts the sequence at step 15 (" in out.why


def test_the_dense_stage_is_kept_when_it_agrees_best():
    prep, seq, gt = _prepared_3d()
    from dm2_backend.pipeline.dense_start import dense_start
    from dm2_backend.pipeline.start import Start, StartKind

    noisy = gt.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.05, (len(gt), 3))
    out = dense_start(seq, prep, Start(noisy, StartKind.GRAPH, "test"), OptimConfig())
    assert out.refined and out.locally_accurate and len(out.dense.history) >= 1
    assert out.dense.agreement_m2["dense"] < out.dense.agreement_m2["graph"]


def test_eliminating_the_planes_gives_the_curvature_of_the_refitted_cost():
    """x^T (H - B S^-1 B^T) x is the curvature of the plane cost with the planes fitted again, along any joint
    move x of the frames: a wrong plane Jacobian G, block B or S would miss it (the planes-held H does not)."""
    cells, gt = street()
    a = planes.assign(cells, gt, VOXEL)
    lin = planes.linearise(a, planes.fit(a, gt), gt)
    rng = np.random.default_rng(4)
    x = rng.normal(0, 1, (len(gt), 6)) * np.array([1e-3] * 3 + [1e-2] * 3)
    x[:, :3] += 2e-3  # a common turn, which the planes follow
    x[:, 3:] += 0.02

    def refitted(eps: float) -> float:
        moved = gt.copy()
        for f in range(len(gt)):
            step = np.eye(4)
            step[:3, :3] = Rotation.from_rotvec(eps * x[f, :3]).as_matrix()
            step[:3, 3] = eps * x[f, 3:]
            moved[f] = gt[f] @ step
        return 0.5 * planes.cost(a, moved)

    eps = 0.1
    curvature = (refitted(eps) - 2 * refitted(0.0) + refitted(-eps)) / eps**2
    flat = x.ravel()
    H = np.einsum("fi,fij,fj->", x, lin.H, x)
    reduced = H - flat @ lin.coupling(flat)
    assert reduced == pytest.approx(curvature, rel=0.05)
    assert reduced < 0.5 * H  # the planes follow a joint move: most of the held curvature is not there


def test_an_interrupted_dense_stage_resumes_where_it_stopped(tmp_path):
    """Interrupted after two rounds, resumed from its checkpoint: the same poses as a run never interrupted;
    a finished stage is returned as it ended; a checkpoint of another start or a damaged one is one line."""
    from dm2_backend.optim import dense_checkpoint
    from dm2_backend.runtime.errors import InputError

    cells, gt = street()
    graph, dead = odometry_graph(gt, 0.01, 0.001, seed=2)
    whole = refine_dense(cells, graph, dead, VOXEL)
    assert len(whole.history) > 3
    ckpt = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    calls = []

    def interrupt(_poses: np.ndarray) -> float:
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return 0.0

    with pytest.raises(KeyboardInterrupt):
        refine_dense(cells, graph, dead, VOXEL, trace=interrupt, checkpoint=ckpt)
    assert dense_checkpoint.load(ckpt, dead, 30).rounds_done == 2
    resumed = refine_dense(cells, graph, dead, VOXEL, checkpoint=ckpt, resume=True)
    assert len(resumed.history) == len(whole.history) and resumed.stopped == whole.stopped
    np.testing.assert_allclose(resumed.poses, whole.poses, atol=1e-9)
    again = refine_dense(cells, graph, dead, VOXEL, checkpoint=ckpt, resume=True)  # the stage had ended
    assert again.seconds == 0.0 and again.stopped == whole.stopped
    np.testing.assert_array_equal(again.poses, resumed.poses)
    with pytest.raises(InputError, match="other start poses"):
        refine_dense(cells, graph, gt, VOXEL, checkpoint=ckpt, resume=True)
    ckpt.write_bytes(ckpt.read_bytes()[:100])
    with pytest.raises(InputError, match="damaged"):
        refine_dense(cells, graph, dead, VOXEL, checkpoint=ckpt, resume=True)


def test_a_frame_over_its_share_keeps_that_many_exact_cells_twice_as_large():
    rng = np.random.default_rng(4)
    many = rng.uniform(-3, 3, (20000, 3))  # over 100 cells of 1 m, far more of 0.5 m
    few = rng.uniform(0, 0.9, (500, 3))  # a few cells of 0.5 m
    seq = ScanSequence(lambda i: Scan([many, few][i]), 2, planar=False)
    cells = planes.cells_from_scans(seq, 0.5, 100, 10**6)
    k_few = len(planes.compress(few, 0.5)[0])
    assert cells.size == 0.5 and np.bincount(cells.frame).tolist() == [100, k_few]
    coarse = planes.compress(many, 1.0)
    assert len(coarse[0]) > 100
    first = cells.frame == 0
    gap = np.linalg.norm(cells.mean[first].astype(np.float64)[:, None] - coarse[1][None], axis=2)
    found = gap.argmin(1).tolist()
    assert gap.min(1).max() < 1e-5
    assert len(set(found)) == 100  # distinct cells of the coarse size, each summed over all its points
    for i, count, scatter in zip(found, cells.count[first], cells.scatter[first], strict=True):
        np.testing.assert_allclose(count, coarse[0][i])
        np.testing.assert_allclose(scatter, coarse[2][i], rtol=1e-5, atol=1e-5)


def _mapped_resident_kib(path: Path) -> int:
    """Resident KiB of this process's mappings of ``path`` (Linux ``smaps``)."""
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        if re.match(r"[0-9a-f]+-[0-9a-f]+ ", line):  # a mapping's header: address range, ..., its file
            inside = line.rstrip().endswith(str(path))
        elif inside and line.startswith("Rss:"):
            total += int(line.split()[1])
    return total


def test_released_mapped_pages_leave_the_memory_and_are_read_again_where_touched(tmp_path):
    path = tmp_path / "points.npy"
    np.save(path, np.arange(3_000_000, dtype=np.float32).reshape(-1, 3))  # 11 MiB
    mapped = np.asarray(np.load(path, mmap_mode="r"))
    views = [mapped[i : i + 1000] for i in range(0, len(mapped), 1000)]
    total = float(mapped.sum(dtype=np.float64))
    linux = Path("/proc/self/smaps").is_file()
    if linux:
        assert _mapped_resident_kib(path) > 10_000  # touched: resident
    assert release_mapped(views) == 1  # one file behind all the views
    if linux:
        assert _mapped_resident_kib(path) < 1_000
    assert float(mapped.sum(dtype=np.float64)) == total
    copy_on_write = np.load(tmp_path / "points.npy", mmap_mode="c")
    assert release_mapped([np.zeros(3), copy_on_write[:10]]) == 0  # in memory, or possibly written to: left alone


def test_group_rows_numbers_the_keys_in_their_order():
    rng = np.random.default_rng(5)
    for keys in (rng.integers(-4, 4, (500, 3)), rng.integers(-2**40, 2**40, (50, 3)),
                 rng.integers(-3, 3, (300, 3)).astype(np.int32) * 50_000):
        inv, n = group_rows(keys)
        unique, expected = np.unique(keys.astype(np.int64), axis=0, return_inverse=True)
        assert n == len(unique) and np.array_equal(inv, expected.ravel())


def test_block_rows_are_the_csr_of_the_blocks():
    rng = np.random.default_rng(6)
    frame = np.array([0, 0, 0, 2, 3, 3])  # frame 1 has no pair, voxels ascending within a frame
    voxel = np.array([0, 2, 4, 1, 0, 4])
    blocks = rng.normal(size=(6, 6, 3))
    built = planes._BlockRows(frame, 5, 6, 3)
    built.put(slice(0, 4), voxel[:4], blocks[:4])
    built.put(slice(4, 6), voxel[4:], blocks[4:])
    expected = bsr_matrix((blocks, voxel, np.searchsorted(frame, np.arange(6))), shape=(30, 15)).toarray()
    assert np.array_equal(built.matrix(15).toarray(), expected)


def panel_seen_from_both_sides() -> tuple[planes.Cells, np.ndarray, np.ndarray]:
    """A 4 cm thick panel (faces at x = 0.38 and 0.42 m, inside one 0.8 m voxel), four frames in front of each
    face seeing only that face (2 mm noise): the cells, the true poses and each frame's side (-1, +1)."""
    rng = np.random.default_rng(5)
    side = np.repeat([-1, 1], 4)
    poses = np.tile(np.eye(4), (8, 1, 1))
    poses[:, 0, 3] = np.where(side < 0, -0.6, 1.4)
    poses[:, 1, 3] = np.tile(np.linspace(0.1, 0.7, 4), 2)
    scans = []
    for s, T in zip(side, poses, strict=True):
        yz = rng.uniform([0.05, 0.05], [0.75, 0.75], (3000, 2))
        face = np.column_stack([np.full(3000, 0.4 + 0.02 * s), yz]) + rng.normal(0, 0.002, (3000, 3))
        scans.append(face - T[:3, 3])
    seq = ScanSequence(lambda i: Scan(scans[i]), 8, planar=False)
    return planes.cells_from_scans(seq, 0.1, 2048, 10**6), poses, side


def test_only_the_voxels_with_cells_on_both_sides_are_grouped_again():
    """The side pass regroups the cells of the voxels that hold both sides and keeps the first pass's planes for the
    others: the same planes, in the same order, as grouping every cell again by voxel and side."""
    cells, poses, _ = panel_seen_from_both_sides()
    todo = np.arange(len(cells))
    frame_of = cells.frame.astype(np.int64)
    mean = (poses[frame_of, :3, :3] @ cells.mean.astype(np.float64)[:, :, None])[:, :, 0] + poses[frame_of, :3, 3]
    ref = np.ones(len(cells))
    size = 0.8
    first = planes._voxel_planes(cells, todo, mean, frame_of, ref, poses, size)
    back = planes._behind(todo, mean, frame_of, poses, first.candidate, first.normal, first.inv, first.n)
    assert 0 < back.sum() < len(back)  # the panel's two faces: some voxels hold both sides
    split = planes._split_sides(cells, todo, mean, frame_of, ref, poses, size, first, back)
    every = planes._voxel_planes(cells, todo, mean, frame_of, ref, poses, size, back)
    assert split.n == every.n and len(split.candidate) == len(every.candidate)
    assert np.all(np.diff(split.candidate) > 0)  # ascending: the planes' numbers follow the voxels'

    def planes_of(v):  # each candidate voxel as (its cells, normal up to sign, eigenvalues), in candidate order
        members = [tuple(np.flatnonzero(v.inv == c)) for c in v.candidate]
        return members, np.abs(v.normal), v.lam

    got, want = planes_of(split), planes_of(every)
    order = sorted(range(len(want[0])), key=lambda k: want[0][k])
    mine = sorted(range(len(got[0])), key=lambda k: got[0][k])
    assert [got[0][k] for k in mine] == [want[0][k] for k in order]
    np.testing.assert_allclose(got[1][mine], want[1][order], atol=1e-9)
    np.testing.assert_allclose(got[2][mine], want[2][order], rtol=1e-9, atol=1e-12)


def test_the_two_faces_of_a_panel_are_two_planes(monkeypatch):
    cells, poses, side = panel_seen_from_both_sides()
    a = planes.assign(cells, poses, 0.8)
    sides = {v: set(side[a.frame[a.voxel == v]]) for v in np.unique(a.voxel)}
    assert len(sides) >= 2 and all(len(s) == 1 for s in sides.values()), sides
    assert np.nanmax(planes.disagreement(a, poses)) < 0.004**2  # each frame on its face's plane, to the noise
    # one plane for both faces (what the split prevents) puts every frame 2 cm off it
    monkeypatch.setattr(planes, "_behind", lambda todo, *args: np.zeros(len(todo), bool))
    merged = planes.assign(cells, poses, 0.8)
    assert any(len(set(side[merged.frame[merged.voxel == v]])) == 2 for v in np.unique(merged.voxel))
    assert np.nanmin(planes.disagreement(merged, poses)) > 0.015**2


def _corner_seen_obliquely(sigma: float, n: int = 30, seed: int = 0) -> tuple[ScanSequence, np.ndarray]:
    """A floor and two walls (2.5 m) seen from 2.6 m by ``n`` cameras on an arc, each point's range noisy by
    ``sigma`` along its beam (as a depth camera's or a LiDAR's), and the true poses."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.3, 1.27, n)
    eyes = np.stack([0.3 + 2.6 * np.cos(angle), 0.3 + 2.6 * np.sin(angle), np.full(n, 1.4)], 1)
    gt = np.tile(np.eye(4), (n, 1, 1))
    for T, eye in zip(gt, eyes, strict=True):
        z = (np.array([0.6, 0.6, 0.5]) - eye) / np.linalg.norm(np.array([0.6, 0.6, 0.5]) - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        T[:3, :3], T[:3, 3] = np.stack([x, np.cross(z, x), z], 1), eye
    a, b = (g.ravel() for g in np.meshgrid(np.linspace(0.02, 2.5, 90), np.linspace(0.02, 2.5, 90)))
    zero = np.zeros_like(a)
    world = np.concatenate([np.stack(c, 1) for c in ((a, b, zero), (zero, a, b), (a, zero, b))])
    scans = []
    for T in gt:
        p = se3.transform_points(se3.inverse(T), world)
        p = p[p[:, 2] > 0.3]
        beam = p / np.linalg.norm(p, axis=1, keepdims=True)
        scans.append((p + beam * rng.normal(0, sigma, (len(p), 1))).astype(np.float32))
    return ScanSequence(lambda i: Scan(scans[i]), n, planar=False), gt


def test_beam_noise_does_not_turn_the_frames_when_thick_cells_are_taken_at_their_means():
    """From the truth, with 5 cm of range noise along the beams: the cells' scatter (their thickness, here mostly
    that noise) turns the frames away from the truth round after round; without it in the thick cells the frames
    stay."""
    seq, gt = _corner_seen_obliquely(0.05)
    graph, _ = odometry_graph(gt, 0.05, 0.02)
    graph.relative = se3.relative(gt[:-1], gt[1:])  # exact odometry, weakly weighed: the planes decide
    moved = {}
    for which in ("all", "thin", "none"):
        cells = planes.cells_from_scans(seq, 0.1, 2048, 10**6, keep_scatter=which)
        with_scatter = (np.abs(cells.scatter).max(1) > 0).mean()  # ("all": a cell of one point has none)
        assert {"all": with_scatter > 0.8, "thin": with_scatter < 0.2, "none": with_scatter == 0}[which]
        moved[which] = ate_rmse(gt, refine_dense(cells, graph, gt, 0.4).poses)
    assert moved["thin"] < 0.005 and moved["all"] > 5 * moved["thin"]


def test_range_noise_does_not_turn_the_frames_through_the_cells():
    """From the truth, with 5 cm of range noise along the beams: cells along the beams leave the frames where
    they are; a cubic grid, whose edges cut a surface's noisy ranges into a near and a far cell, turns them (the
    dense stage's cells: 0.8 mm against 1.9 mm)."""
    seq, gt = _corner_seen_obliquely(0.05)
    graph, _ = odometry_graph(gt, 0.05, 0.02)
    graph.relative = se3.relative(gt[:-1], gt[1:])  # exact odometry, weakly weighed: the planes decide
    along_beams = ate_rmse(gt, refine_dense(planes.cells_from_scans(seq, 0.1, 2048, 10**6, keep_scatter="thin"),
                                            graph, gt, 0.4).poses)

    cut = ate_rmse(gt, refine_dense(planes.cells_from_scans(seq, 0.1, 2048, 10**6, keep_scatter="thin",
                                                            along_beams=False), graph, gt, 0.4).poses)
    assert along_beams < 0.0012 and cut > 2 * along_beams


def test_thin_cells_keep_their_scatter_and_thick_ones_do_not():
    rng = np.random.default_rng(0)
    width = rng.uniform(-0.05, 0.05, (200, 2))
    cells = []
    for thickness in (0.002, 0.005, 0.012, 0.05):  # a 10 cm square (its width's std 2.9 cm) this thick
        pts = np.column_stack([width, rng.normal(0, thickness, 200)])
        cells.append(planes.compress(pts, 1.0)[2][0])
    kept = planes.kept_scatter(np.stack(cells), "thin")
    assert kept.tolist() == [True, True, False, False]  # thin: under a quarter of the width's std, 7 mm
    assert planes.kept_scatter(np.stack(cells), "all").all() and not planes.kept_scatter(np.stack(cells), "none").any()

