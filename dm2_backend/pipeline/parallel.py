"""One ``dm2 refine`` in several processes: spawned here (``--nproc N``, torch.multiprocessing) or started by
``torchrun`` (detected from its environment), each optimising its share of every step (see
:mod:`dm2_backend.optim.distributed`).

The preparation runs once before the optimisation: in the parent before it spawns the ranks, or under
torchrun on rank 0 first, then on the first process of each other node (a no-op when the nodes share the
cache folder), while the others wait. Every rank then reads the prepared data from the cache, memory-mapped.
Only rank 0 (or the parent of spawned ranks) writes the run folder.
"""

from __future__ import annotations

import contextlib
import enum
import os
import pickle
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as td
import torch.multiprocessing as mp
from torch.multiprocessing.spawn import ProcessException

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.config.schema import RunConfig
from dm2_backend.optim.derived import sampled_points
from dm2_backend.optim.distributed import Dist, init, rank_device, wait_group
from dm2_backend.optim.problem import Execution, Problem, Watch
from dm2_backend.optim.trainer import Optimiser, OptimResult, sample_points
from dm2_backend.pipeline.start import Start
from dm2_backend.prepare import store
from dm2_backend.prepare.cache_keys import code_fingerprint, step_key
from dm2_backend.prepare.steps import Prepared, load_prepared, prepare
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.memory import peak_rss_mb


class Mode(enum.Enum):
    """How a run uses processes: one, a parent spawning ``--nproc`` ranks, or one rank started by torchrun."""

    SINGLE = "single"
    SPAWN = "spawn"
    TORCHRUN = "torchrun"


@dataclass
class Session:
    """How this process takes part in a run: its :class:`Mode` (with spawn the parent of ``dist.world`` ranks,
    with torchrun rank ``dist.rank``); ``cache`` the preparation cache of the run (a temporary folder when the
    run has none but several processes)."""

    dist: Dist
    mode: Mode
    cache: Path | None
    scratch: Path | None = None
    group: object = None  # torchrun: a gloo group with a long timeout, for waiting on single-rank work


@contextlib.contextmanager
def session(nproc: int, cache_dir: Path | None, device: str) -> Iterator[Session]:
    env = Dist.from_env()
    if env.enabled:  # started by torchrun
        torch.set_num_threads(1)
        init(env, rank_device(device, env))
        group = wait_group()
        launch = f"{os.environ.get('TORCHELASTIC_RUN_ID', '')}-{os.environ.get('MASTER_PORT', '')}"
        cache = cache_dir or Path(tempfile.gettempdir()) / f"dm2-torchrun-{launch}"  # one per node
        try:
            yield Session(env, Mode.TORCHRUN, cache, group=group)
            td.barrier(group=group)  # the other ranks wait for rank 0's outputs
        finally:
            if cache_dir is None and env.local_rank == 0:
                shutil.rmtree(cache, ignore_errors=True)
            td.destroy_process_group()
    elif nproc > 1:
        if device == "cuda" and torch.cuda.device_count() < nproc:
            raise InputError(None, f"--nproc {nproc} with --device cuda needs {nproc} GPUs; "
                                   f"{torch.cuda.device_count()} visible")
        with tempfile.TemporaryDirectory(prefix="dm2-nproc-") as tmp:
            yield Session(Dist(0, nproc), Mode.SPAWN, cache_dir or Path(tmp) / "cache", Path(tmp))
    else:
        yield Session(Dist(), Mode.SINGLE, cache_dir)


def prepare_once(inputs, cfg: RunConfig, sess: Session, progress: bool) -> tuple[Prepared, str | None]:
    """The prepared data, and with several processes the cache entry of the points sampled for the optimiser
    (written once, memory-mapped by every rank)."""
    if sess.mode is not Mode.TORCHRUN:
        prep = prepare(inputs.scans, inputs.given, cfg, sess.cache, progress)
        return prep, samples_entry(sess.cache, prep, cfg.optimiser, cfg.seed) if sess.mode is Mode.SPAWN else None
    d = sess.dist
    prep, name = None, None
    for turn in (d.rank == 0, d.local_rank == 0 and d.rank != 0, d.local_rank != 0):
        if turn:  # rank 0 fills the cache, then one process per node (if not shared), then the rest read it
            prep = prepare(inputs.scans, inputs.given, cfg, sess.cache, progress and d.rank == 0)
            name = samples_entry(sess.cache, prep, cfg.optimiser, cfg.seed)
        td.barrier(group=sess.group)
    return prep, name


def samples_entry(cache: Path, prep: Prepared, cfg: OptimConfig, seed: int) -> str:
    """Cache entry of :func:`sample_points` for these frames (the same points the optimiser would draw)."""
    m = sampled_points(cfg, prep.frames.max_points, prep.frames.planar)
    name = f"samples-{step_key(prep.keys['frames'], m, seed, code_fingerprint(sample_points))}"
    if store.get(cache, name) is None:
        store.put(cache, name, {"samples": sample_points(prep.frames, m, seed)})
    return name


def build(prep: Prepared, start: Start, cfg: RunConfig, watch: Watch | None = None,
          progress: bool = True, samples: np.ndarray | None = None, dist: Dist | None = None) -> Optimiser:
    """The optimiser of a run (one construction for every launch mode), starting from ``start``."""
    dist = dist or Dist()
    watch = watch if dist.rank == 0 and watch is not None else Watch()
    device = str(rank_device(cfg.device, dist)) if dist.enabled else cfg.device
    problem = Problem(prep.frames, prep.topology, prep.pairwise, start.poses, start.locally_accurate,
                      start.dense_ran)
    return Optimiser(problem, cfg.optimiser, Execution(cfg.seed, device, progress and dist.rank == 0, samples, dist),
                     watch)


def optimise_rank(prep: Prepared, start: Start, samples: str, cfg: RunConfig, sess: Session,
                  out: Path, resume: bool, progress: bool, watch: Watch) -> tuple[OptimResult, str]:
    """This torchrun rank's part of the optimisation; rank 0's result is the run's."""
    points = store.get(sess.cache, samples)[0]["samples"]
    opt = build(prep, start, cfg, watch, progress, points, sess.dist)
    return opt.run(checkpoint_dir=out, resume=resume), str(opt.device)


# ---------------------------------------------------------------- spawned ranks
@dataclass
class Job:
    """What a spawned rank needs (picklable: no scans, the prepared data is read from the cache)."""

    cache: Path
    keys: dict[str, str]
    start: Start
    samples: str
    cfg: RunConfig
    out: Path
    resume: bool
    progress: bool
    watch: Watch
    world: int
    scratch: Path

    @property
    def result(self) -> Path:
        return self.scratch / "result.pt"


def run_rank(rank: int, job: Job) -> OptimResult:
    """One spawned rank: join the group (a file store in the scratch folder), load, optimise; rank 0 leaves
    its result (and its peak memory) in the scratch folder for the parent."""
    torch.set_num_threads(1)
    dist = Dist(rank, job.world, rank)
    init(dist, rank_device(job.cfg.device, dist), f"file://{job.scratch / 'store'}")
    try:
        prep = load_prepared(job.cache, job.keys)
        points = store.get(job.cache, job.samples)[0]["samples"]
        opt = build(prep, job.start, job.cfg, job.watch, job.progress, points, dist)
        result = opt.run(checkpoint_dir=job.out, resume=job.resume)
        if rank == 0:
            peak = peak_rss_mb()
            torch.save({"result": result, "device": str(opt.device), "rank_peak_rss_mb": peak}, job.result)
        return result
    finally:
        td.destroy_process_group()


#: seconds a failed rank may take to exit before every rank is stopped
FAILED_RANK_GRACE_S = 10.0


def spawn(job: Job, worker: Callable[[int, Job], None] = run_rank) -> dict:
    """Run ``worker`` in ``job.world`` processes; returns what rank 0 left. A failing rank stops the others
    and raises here (a RuntimeError with the errors of the ranks that failed, rank 0's first); so does Ctrl-C."""
    # a fork server that has imported the rank's modules (torch) once starts the ranks in a fraction of
    # the time of fresh interpreters, and unlike a plain fork it holds no threads of the parent
    mp.get_context("forkserver").set_forkserver_preload([__name__, "torch._dynamo", "dm2_backend.pipeline.live"])
    ctx = mp.start_processes(worker, args=(job,), nprocs=job.world, join=False, start_method="forkserver")
    try:
        failed_at = None
        while not ctx.join(timeout=1.0):
            # a rank that failed (its error file written) but hangs on its way out (a gloo thread still waiting on
            # a peer inside a collective) would keep join() waiting for ever: stop them all after a grace period
            if failed_at is None and any(os.path.exists(path) for path in ctx.error_files):
                failed_at = time.monotonic()
            elif failed_at is not None and time.monotonic() - failed_at > FAILED_RANK_GRACE_S:
                raise RuntimeError(_failures(ctx) or "a rank failed and did not exit")
    except ProcessException as exc:
        raise RuntimeError(_failures(ctx) or str(exc)) from None
    finally:
        for proc in ctx.processes:
            if proc.is_alive():
                proc.terminate()
                proc.join(10)
    return torch.load(job.result, weights_only=False)


def _failures(ctx) -> str:
    """The tracebacks the failed ranks left (a rank failing first usually makes the others fail too)."""
    errors = []
    for rank, path in enumerate(ctx.error_files):
        if os.path.exists(path):
            try:
                with open(path, "rb") as fh:
                    errors.append(f"rank {rank} failed:\n{pickle.load(fh)}")
            except (EOFError, pickle.UnpicklingError):  # stopped (by another rank's failure) while writing it
                errors.append(f"rank {rank} failed (stopped while it wrote its error)")
            os.unlink(path)
    return "\n".join(errors)
