"""Distributed optimisation: ``dm2 refine --nproc 2`` (two gloo processes on the CPU) reaches the single-process
result within a tolerance, only rank 0 writes, every rank ends with the same parameters, ``--resume`` of an
interrupted distributed run equals the uninterrupted one; and the memory-mapped preparation cache."""

from __future__ import annotations

import json
import os
import pickle
import time
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from optim_cases import one_thread, planar_case, write_planar_sequence
from shared_helpers import run as dm2

from dm2_backend import config
from dm2_backend.cli.options import read_options
from dm2_backend.optim.checkpoint import CHECKPOINT
from dm2_backend.optim.distributed import Dist, shard
from dm2_backend.optim.problem import Watch
from dm2_backend.optim.trainer import sample_points
from dm2_backend.pipeline import parallel
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.pipeline.run_writer import map_entropy, map_sampler
from dm2_backend.pipeline.start import choose_start
from dm2_backend.prepare import store
from dm2_backend.prepare.steps import load_prepared


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


EPOCHS = 4
SMALL = {
    "seed": 3,
    "frames": {"max_points": 256},
    "optimiser": {"epochs": EPOCHS, "max_steps": 0, "points_per_frame": 64, "bce_points_per_frame": 32,
                  "batch_groups": 16, "grid_max_cells": 2**14, "dense": False},  # the first-order epochs
}
#: Two ranks do not repeat the single-process arithmetic: rank 1 draws its own free-space samples, each rank
#: normalises its loss terms over its half of the anchors (a frame in the groups of anchors on both ranks
#: counts on both), and the gradients are summed in another order. 1 cm is 1/80 of the largest correction
#: (0.8 m) and 1/35 of how far the result moves with another seed (0.35 m); the measured gap is 2 mm.
TOLERANCE_M = 0.01


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return write_planar_sequence(tmp_path_factory.mktemp("seq"), SMALL)


def refine(seq: Path, out: Path, cache: Path, *extra: str):
    result = dm2("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--gt",
                 str(seq / "poses.txt"), "--out", str(out), "-c", str(seq / "config.yaml"), "--cache-dir",
                 str(cache), "-q", *extra)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def runs(seq, tmp_path_factory) -> dict:
    """The same refinement in one process and in two (the CLI), sharing one preparation cache."""
    root = tmp_path_factory.mktemp("runs")
    one = refine(seq, root / "one", root / "cache")
    two = refine(seq, root / "two", root / "cache", "--nproc", "2")
    return {"root": root, "one": one, "two": two}


def positions_of(path: Path) -> np.ndarray:
    return np.load(path)[:, :3, 3]


def positions(folder: Path) -> np.ndarray:
    return positions_of(folder / "poses.npy")


def test_two_processes_match_one(runs):
    root, one, two = runs["root"], runs["one"], runs["two"]
    assert one["processes"] == 1 and two["processes"] == 2 and two["device"] == "cpu"
    assert two["prepare"]["cached"] == dict.fromkeys(two["prepare"]["cached"], True)
    p1, p2 = positions(root / "one"), positions(root / "two")
    gap = np.linalg.norm(p1 - p2, axis=1).max()
    moved = np.linalg.norm(p1 - positions_of(root / "one" / "warm_start.npy"), axis=1).max()
    assert gap < TOLERANCE_M, gap
    assert gap > 0  # two processes really split the steps (identical only by accident)
    assert moved > 20 * TOLERANCE_M  # the optimisation moved the poses much more than the tolerance
    m1, m2 = one["metrics"]["ape_trans_rmse_m"], two["metrics"]["ape_trans_rmse_m"]
    assert m2 < 0.8 * two["warm_start_metrics"]["ape_trans_rmse_m"] and abs(m1 - m2) < 0.1 * m1
    assert [e["epoch"] for e in two["epochs"]] == list(range(EPOCHS)) and all("ate" in e for e in two["epochs"])
    # the same run folder, nothing left behind by the ranks
    assert sorted(p.name for p in (root / "two").iterdir()) == sorted(p.name for p in (root / "one").iterdir())
    assert two["files"] == one["files"]


# ---------------------------------------------------------------- resume, and who writes
class Interrupt:
    """Metric that fails at epoch ``at`` (on rank 0, the only rank evaluating it), like a crash."""

    def __init__(self, at: int) -> None:
        self.at, self.calls = at, 0

    def __call__(self, poses: np.ndarray) -> float:
        if self.calls == self.at:
            raise RuntimeError("interrupted")
        self.calls += 1
        return 0.0


def checking_worker(rank: int, job: parallel.Job) -> None:
    """The real rank, recording every file it renames into place (all run-folder writes are atomic) and
    keeping its final poses."""
    log = job.scratch / f"writes-{rank}.txt"
    log.touch()
    real = os.replace

    def replace(src, dst):
        with open(log, "a") as fh:
            fh.write(f"{dst}\n")
        return real(src, dst)

    os.replace = replace
    result = parallel.run_rank(rank, job)
    np.save(job.scratch / f"poses-{rank}.npy", result.poses)


def job(seq: Path, cache: Path, out: Path, scratch: Path, resume: bool, metric, overrides=None) -> parallel.Job:
    """The job ``dm2 refine --nproc 2`` would give its ranks for ``seq``'s config."""
    cfg = config.load(seq / "config.yaml", {"nproc": 2, **(overrides or {})})
    inputs = load_inputs(seq / "velodyne", None, seq / "warm_start.txt", None, read_options())
    sess = parallel.Session(Dist(0, 2), parallel.Mode.SPAWN, cache, scratch)
    prep, samples = parallel.prepare_once(inputs, cfg, sess, progress=False)
    assert all(prep.cached.values())
    sampler = map_sampler(inputs)
    start = choose_start(prep, cfg.optimiser, sampler)
    watch = Watch(metric, map_entropy(sampler))
    return parallel.Job(cache, prep.keys, start, samples, cfg, out, resume, False, watch, 2, scratch)


def test_resume_of_a_distributed_run(seq, runs, tmp_path):
    cache, out = runs["root"] / "cache", tmp_path / "run"
    first = tmp_path / "first"
    first.mkdir()
    with pytest.raises(RuntimeError, match="rank 0 failed:(.|\n)*RuntimeError: interrupted"):
        parallel.spawn(job(seq, cache, out, first, False, Interrupt(EPOCHS // 2)), checking_worker)
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["epoch"] == EPOCHS // 2 - 1
    assert (first / "writes-1.txt").read_text() == ""  # rank 1 wrote nothing
    assert {Path(p).name for p in (first / "writes-0.txt").read_text().split()} == {CHECKPOINT}
    assert sorted(p.name for p in out.iterdir()) == [CHECKPOINT]

    second = tmp_path / "second"
    second.mkdir()
    done = parallel.spawn(job(seq, cache, out, second, True, None), checking_worker)
    result = done["result"]
    assert (second / "writes-1.txt").read_text() == ""
    # every rank resumed from rank 0's checkpoint: they end with the same parameters
    np.testing.assert_array_equal(np.load(second / "poses-0.npy"), np.load(second / "poses-1.npy"))
    assert [row.epoch for row in result.history] == list(range(EPOCHS))
    # the first epochs come from the checkpoint
    assert [row.row() for row in result.history[: EPOCHS // 2]] == state["history"]
    # ... and the resumed run equals the uninterrupted distributed run of the CLI
    uninterrupted = np.load(runs["root"] / "two" / "poses.npy")
    np.testing.assert_array_equal(result.poses[:, :3, 3], uninterrupted[:, :3, 3])
    losses = [e["loss"] for e in runs["two"]["epochs"]]
    assert [row.loss for row in result.history] == losses


def test_unused_field_network_weights_and_a_rank_without_anchors(seq, runs, tmp_path):
    """Without BCE the occupancy field gets no gradient (DDP's unused parameters), L-Net's weights are
    all-reduced too, and with 59 anchors per step the last step has one anchor: rank 1 joins with weight 0."""
    opts = {"optimiser": {"epochs": 1, "use_bce": False, "pose_model": "lnet", "batch_groups": 59}}
    done = parallel.spawn(job(seq, runs["root"] / "cache", tmp_path / "run", tmp_path, False, None, opts),
                          checking_worker)
    result, start = done["result"], np.load(runs["root"] / "one" / "warm_start.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "poses-0.npy"), np.load(tmp_path / "poses-1.npy"))
    assert np.isfinite(result.poses).all() and not np.allclose(result.poses, start)
    assert len(result.history) == 1 and result.history[0].bce is None and np.isfinite(result.history[0].loss)


# ---------------------------------------------------------------- pieces
def test_shard_covers_each_anchor_once():
    anchors = np.arange(10, 17)
    parts = [shard(anchors, Dist(r, 3)) for r in range(3)]
    np.testing.assert_array_equal(np.concatenate([p for p, _ in parts]), anchors)
    assert sum(w for _, w in parts) == pytest.approx(1.0)
    mine, weight = shard(np.array([5]), Dist(1, 2))  # more ranks than anchors: a zero-weight stand-in
    assert weight == 0.0 and list(mine) == [5]


def test_memory_mapped_cache_round_trip(tmp_path):
    frames = planar_case().frames
    store.put_frames(tmp_path, "frames-x", frames)
    arrays, meta = store.get(tmp_path, "frames-x")
    back = store.frames_from(arrays, meta)
    assert isinstance(np.load(tmp_path / "frames-x" / "points.npy", mmap_mode="r"), np.memmap)
    assert len(back) == len(frames) and back.planar == frames.planar and back.scale == frames.scale
    for a, b in zip(back.points, frames.points):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == np.float32 and not a.flags.writeable and not a.flags.owndata  # views of the map
    np.testing.assert_array_equal(back.timestamps, frames.timestamps)
    # the optimiser's sampled points: copy-on-write, shared until written
    samples = sample_points(frames, 16, 0)
    store.put(tmp_path, "samples-x", {"samples": samples})
    mapped = store.get(tmp_path, "samples-x")[0]["samples"]
    np.testing.assert_array_equal(mapped, samples)
    assert mapped.flags.writeable and not mapped.flags.owndata
    mapped[0] = 0  # a private page: the file is unchanged
    np.testing.assert_array_equal(store.get(tmp_path, "samples-x")[0]["samples"], samples)
    assert store.get(tmp_path, "missing") is None and store.get(None, "samples-x") is None


def test_load_prepared_needs_every_entry(tmp_path):
    with pytest.raises(FileNotFoundError, match="frames-x"):
        load_prepared(tmp_path, {"frames": "frames-x"})


def test_nproc_must_be_positive(tmp_path):
    from dm2_backend.runtime.errors import InputError

    with pytest.raises(InputError, match="nproc"):
        config.load(None, {"nproc": 0})
    assert config.load(None).nproc == 1


def stuck_worker(rank: int, job) -> None:
    """Rank 0 fails but cannot exit (a non-daemon thread, like a gloo thread waiting on a peer); rank 1 waits in
    what would be a collective."""
    import threading
    import time

    if rank == 0:
        threading.Thread(target=time.sleep, args=(3600,), daemon=False).start()
        raise RuntimeError("rank 0 broke")
    time.sleep(3600)


def test_a_failed_rank_that_cannot_exit_does_not_hang_the_run(tmp_path, monkeypatch):
    monkeypatch.setattr(parallel, "FAILED_RANK_GRACE_S", 2.0)
    fake = types.SimpleNamespace(world=2, result=tmp_path / "result.pt")
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="rank 0 failed:(.|\n)*rank 0 broke"):
        parallel.spawn(fake, stuck_worker)
    assert time.monotonic() - t0 < 60


def test_a_rank_stopped_while_writing_its_error_does_not_hide_the_others(tmp_path):
    """A rank terminated while it writes its error file leaves it empty: the first rank's error still comes back."""
    first, second = tmp_path / "0.pickle", tmp_path / "1.pickle"
    first.write_bytes(pickle.dumps("Traceback ...\nRuntimeError: interrupted"))
    second.write_bytes(b"")
    text = parallel._failures(types.SimpleNamespace(error_files=[str(first), str(second)]))
    assert "rank 0 failed:\nTraceback ...\nRuntimeError: interrupted" in text
    assert "rank 1 failed (stopped while it wrote its error)" in text
