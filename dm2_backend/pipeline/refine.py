"""``dm2 refine`` as a function: inputs -> prepare -> DeepMapping2 optimiser -> run folder."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path

from dm2_backend.config.schema import RunConfig
from dm2_backend.optim import dense_checkpoint, distributed
from dm2_backend.optim.checkpoint import CHECKPOINT, load_checkpoint
from dm2_backend.optim.problem import Watch
from dm2_backend.pipeline import parallel
from dm2_backend.pipeline.dense_start import DenseCells, dense_start
from dm2_backend.pipeline.inputs import RunInputs
from dm2_backend.pipeline.live import live_metric
from dm2_backend.pipeline.run_report import RunReport
from dm2_backend.pipeline.run_writer import map_entropy, map_sampler, output_timestamps, write_run
from dm2_backend.pipeline.start import choose_start
from dm2_backend.runtime.memory import release_mapped

log = logging.getLogger(__name__)


def check_checkpoints(out: Path, frames: int, rounds: int) -> None:
    """The run folder's checkpoints read and checked as the stages will read them (bounded before decoding,
    ``frames`` finite rigid poses, a plausible epoch or round count): :class:`InputError` naming the file."""
    if (out / dense_checkpoint.DENSE_CHECKPOINT).is_file():
        dense_checkpoint.check(out / dense_checkpoint.DENSE_CHECKPOINT, frames, rounds)
    if (out / CHECKPOINT).is_file():
        load_checkpoint(out / CHECKPOINT, "cpu", frames)


def refine(inputs: RunInputs, cfg: RunConfig, out: Path, cache_dir: Path | None, resume: bool = False,
           progress: bool = True, started: float | None = None) -> RunReport | None:
    """Run the whole pipeline; returns the report (also written to ``out/report.json``); ``started``: when the
    command started (``time.perf_counter``), so that the report's total counts reading and writing too. With
    ``cfg.nproc > 1`` the optimisation runs in that many spawned processes; started by torchrun, this
    process is one rank, and ranks other than 0 return None (they write nothing)."""
    t_start = time.perf_counter()
    stamps = output_timestamps(inputs)
    if resume:  # a damaged or foreign checkpoint is one line now, not after the preparation
        check_checkpoints(out, len(inputs.scans), cfg.optimiser.dense_rounds)
    with parallel.session(cfg.nproc, cache_dir, cfg.device) as sess:
        lead = sess.dist.rank == 0
        if lead:
            out.mkdir(parents=True, exist_ok=True)
        prep, samples = parallel.prepare_once(inputs, cfg, sess, progress)
        stages = prep.stages.copy()
        with stages.stage("map_sampler"):
            sampler = map_sampler(inputs, progress) if lead else None
        cells = None
        with stages.stage("start"):  # with the dense stage's cells, which judge the graph start
            if lead and cfg.optimiser.dense:
                release_mapped(prep.frames.points)  # the cells are read from the scans; the graph needs no points
                cells = DenseCells.of(inputs.scans, prep, cfg.optimiser, cfg.seed, progress)
            start = choose_start(prep, cfg.optimiser, sampler, cells) if lead else None
        metric = live_metric(inputs, stamps) if lead else None
        with stages.stage("dense"):
            if lead:
                start = dense_start(inputs.scans, prep, start, cfg.optimiser, cfg.seed, progress, metric,
                                    checkpoint_dir=out, resume=resume, dense_cells=cells)
            cells = None  # the epochs and the outputs do not read them
            if sess.mode is parallel.Mode.TORCHRUN:
                start = distributed.broadcast(start)
        watch = Watch(metric, map_entropy(sampler), metric) if lead else None
        extra = {}
        if sess.mode is parallel.Mode.SINGLE:
            with stages.stage("optimise"):  # with building the optimiser, as the other modes
                opt = parallel.build(prep, start, cfg, watch, progress)
                result, device = opt.run(checkpoint_dir=out, resume=resume), str(opt.device)
        elif sess.mode is parallel.Mode.SPAWN:  # timed with starting the processes and building their optimisers
            with stages.stage("optimise"):
                job = parallel.Job(sess.cache, prep.keys, start, samples, cfg, out, resume, progress,
                                   watch, sess.dist.world, sess.scratch)
                done = parallel.spawn(job)
            result, device, extra["rank_peak_rss_mb"] = done["result"], done["device"], done["rank_peak_rss_mb"]
        else:
            with stages.stage("optimise"):
                result, device = parallel.optimise_rank(prep, start, samples, cfg, sess, out, resume,
                                                        progress, watch)
        if not lead:
            return None
        extra.update(best_epoch=result.best_epoch, selection=result.selection, start=start.summary(),
                     stopped=result.stopped.detail if result.stopped.failed else None,
                     stop_reason=result.stopped.reason.value, derived=asdict(result.derived), device=device,
                     processes=sess.dist.world)
        return write_run(out, cfg, inputs, prep, result.poses, "dm2 refine", stages, extra, result.history,
                         sampler=sampler, start=start.poses, started=t_start if started is None else started)
