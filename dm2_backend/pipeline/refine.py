"""``dm2 refine`` as a function: inputs -> prepare -> DeepMapping2 optimiser -> run folder."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from dm2_backend import __version__, config
from dm2_backend.errors import InputError
from dm2_backend.evaluation import plots
from dm2_backend.evaluation.ape_rpe import evaluate_poses
from dm2_backend.evaluation.map_quality import MapSampler
from dm2_backend.evaluation.paper_ate import paper_ate
from dm2_backend.evaluation.relations import relations_error
from dm2_backend.evaluation.report import EstimateReport, run_metrics
from dm2_backend.maps.run_maps import write_run_maps
from dm2_backend.optim import distributed
from dm2_backend.optim.config import OptimConfig
from dm2_backend.pipeline import outputs, parallel
from dm2_backend.pipeline.inputs import RunInputs
from dm2_backend.pipeline.live import ate_rmse, live_metric  # noqa: F401 (ate_rmse: also imported from here)
from dm2_backend.pipeline.start import choose_start
from dm2_backend.prepare.pipeline import Prepared
from dm2_backend.trajectory import Trajectory

log = logging.getLogger(__name__)


def metrics_of(traj: Trajectory, inputs: RunInputs) -> dict[str, float]:
    """Accuracy of ``traj`` against the ground truth / relations given to the run (empty without). An
    evaluation that fails is recorded as ``{"error": ...}`` so the run's outputs are still written."""
    try:
        return _metrics(traj, inputs)
    except InputError as exc:
        log.warning("evaluation failed: %s", exc.message)
        return {"error": exc.message}


def _metrics(traj: Trajectory, inputs: RunInputs) -> dict[str, float]:
    est = EstimateReport(label="", path="")
    if inputs.gt is not None:
        gt = replace(inputs.gt, timestamps=None)
        matched = traj if inputs.gt_frames is None else traj.subset(inputs.gt_frames)
        est.poses = evaluate_poses(gt, replace(matched, timestamps=None), align="se3")
        est.paper = paper_ate(inputs.gt.poses, matched.poses)
    if inputs.relations is not None and traj.timestamps is not None:
        est.relations = relations_error(traj, inputs.relations)
    return run_metrics(est)


def output_timestamps(inputs: RunInputs) -> np.ndarray:
    if inputs.scans.timestamps is not None:
        return inputs.scans.timestamps
    if inputs.given is not None and inputs.given.timestamps is not None:
        return inputs.given.timestamps
    return np.arange(len(inputs.scans), dtype=np.float64)


def trajectory_of(poses: np.ndarray, inputs: RunInputs) -> Trajectory:
    """The run's poses as a trajectory for the writers: the output stamps, the CARMEN template, and the KITTI
    calibration when camera-frame poses came in (outputs go back to that frame)."""
    meta = {}
    if inputs.given_format == "carmen":
        meta["carmen_template"] = inputs.scans.source  # the CARMEN writer rewrites the log's own poses
    calib = next((t.meta["calib"] for t in (inputs.given, inputs.gt) if t is not None and t.meta.get("calib")), None)
    if calib:
        meta["calib"] = calib
    return Trajectory(poses, output_timestamps(inputs), planar=inputs.scans.planar, meta=meta)


def map_sampler(inputs: RunInputs, progress: bool = False) -> MapSampler:
    """The scans voxelised once for the map metrics of every pose set of the run."""
    return MapSampler.from_scans(inputs.scans, progress=progress)


def map_entropy(sampler: MapSampler | None) -> Callable[[np.ndarray], float] | None:
    return None if sampler is None else sampler.entropy


def map_metrics(sampler: MapSampler, poses: np.ndarray) -> dict[str, float]:
    q = sampler.evaluate(poses)
    return {"map_entropy": q.entropy, "map_plane_variance_m2": q.plane_variance}


def write_common(out: Path, cfg: dict, inputs: RunInputs, prep: Prepared, final: np.ndarray, method: str,
                 timings: dict, extra: dict | None = None, epochs: list[dict] | None = None,
                 sampler: MapSampler | None = None, start: np.ndarray | None = None) -> dict:
    """The parts of a run folder shared by ``refine`` and ``baseline``; returns the report. ``sampler``: the
    scans prepared for the map metrics (made here when None); ``start``: where the optimiser started."""
    out.mkdir(parents=True, exist_ok=True)
    sampler = sampler or map_sampler(inputs)
    stages = {"warm_start": prep.warm_start, "loop_closed": prep.topology.poses, "start": start, "final": final}
    maps = {name: map_metrics(sampler, poses) for name, poses in stages.items() if poses is not None}
    config.dump(cfg, out / "config.yaml")
    config.dump(prep.resolved, out / "resolved.yaml")  # the plugins as run: ``auto`` resolved
    warm_traj = trajectory_of(prep.warm_start, inputs)
    final_traj = trajectory_of(final, inputs)
    files = outputs.write_trajectories(out, final_traj, inputs.given_path, inputs.given_format)
    files += outputs.write_trajectories(out, warm_traj, None, None, stem="warm_start")
    outputs.write_map(out / "map.ply", prep.frames, final, 2 * prep.frames.scale.get("spacing", 0.0))
    files += write_run_maps(out, inputs.scans, final, prep.frames.planar)  # map.pgm/.yaml, octomap.bt, M-Net maps
    outputs.write_prior_files(out / "prior", prep.warm_start, prep.topology, prep.pairwise)
    per_frame = None
    if inputs.gt is not None:
        per_frame = {"translation error": (paper_ate(inputs.gt.poses, inputs.at_gt(final)).trans_errors, "m")}
    drawn = {"warm start": inputs.at_gt(prep.warm_start), method: inputs.at_gt(final)}  # where gt is known
    outputs.write_plots(out, drawn, inputs.gt, per_frame, None)
    files += outputs.write_topology(out, prep.topology, final)
    report = {
        "method": method,
        "dm2_version": __version__,
        "frames": len(prep.frames),
        "planar": prep.frames.planar,
        **({"ground_truth_scans": len(inputs.gt)} if inputs.gt is not None else {}),
        "metrics": {**metrics_of(final_traj, inputs), **maps["final"]},
        "warm_start_metrics": {**metrics_of(warm_traj, inputs), **maps["warm_start"]},
        **({"loop_closed_metrics": {**metrics_of(trajectory_of(prep.topology.poses, inputs), inputs),
                                    **maps["loop_closed"]}}
           if prep.topology.poses is not None else {}),
        **({"start_metrics": {**metrics_of(trajectory_of(start, inputs), inputs), **maps["start"]}}
           if start is not None else {}),
        "map_quality": sampler.settings_summary(),
        "timings": timings,
        "peak_rss_mb": outputs.peak_rss_mb(),
        "prepare": {
            "cached": prep.cached,
            "scale": prep.frames.scale,
            "topology_edges": int(len(prep.topology.edges)),
            "pairs": int((prep.topology.groups >= 0).sum()),
            "pairs_valid": int(prep.pairwise.valid.sum()),
        },
        "files": files,
        **(extra or {}),
    }
    if epochs is not None:
        report["epochs"] = epochs
        plots.plot_run_epochs(out / "epochs.png", report)  # from the start (epoch 0) on
    outputs.write_report(out / "report.json", report)
    return report


def refine(inputs: RunInputs, cfg: dict, out: Path, cache_dir: Path | None, resume: bool = False,
           progress: bool = True) -> dict | None:
    """Run the whole pipeline; returns the report (also written to ``out/report.json``). With
    ``cfg["nproc"] > 1`` the optimisation runs in that many spawned processes; started by torchrun, this
    process is one rank, and ranks other than 0 return None (they write nothing)."""
    t_start = time.perf_counter()
    ocfg = OptimConfig.from_dict(cfg["optimiser"])
    stamps = output_timestamps(inputs)
    with parallel.session(int(cfg.get("nproc", 1)), cache_dir, cfg["device"]) as sess:
        lead = sess.dist.rank == 0
        if lead:
            out.mkdir(parents=True, exist_ok=True)
        prep, samples = parallel.prepare_once(inputs, cfg, ocfg, sess, progress)
        t_map = time.perf_counter()
        sampler = map_sampler(inputs, progress) if lead else None
        start = choose_start(prep, ocfg, sampler) if lead else None
        if sess.mode == "torchrun":
            start = distributed.broadcast(start)
        t_map = time.perf_counter() - t_map
        watch = parallel.Watch(live_metric(inputs, stamps), map_entropy(sampler)) if lead else None
        extra = {}
        if sess.mode == "single":
            opt = parallel.build(prep, start, ocfg, cfg, watch, progress)
            t_opt = time.perf_counter()
            result, device = opt.run(checkpoint_dir=out, resume=resume), str(opt.device)
        elif sess.mode == "spawn":  # timed with starting the processes and building their optimisers
            t_opt = time.perf_counter()
            job = parallel.Job(sess.cache, prep.keys, start, samples, ocfg, cfg, out, resume, progress,
                               watch, sess.dist.world, sess.scratch)
            done = parallel.spawn(job)
            result, device, extra["rank_peak_rss_mb"] = done["result"], done["device"], done["rank_peak_rss_mb"]
        else:
            t_opt = time.perf_counter()
            result, device = parallel.optimise_rank(prep, start, samples, ocfg, cfg, sess, out, resume,
                                                    progress, watch)
        if not lead:
            return None
        timings = dict(prep.timings)
        timings["start"] = t_map
        timings["optimise"] = time.perf_counter() - t_opt
        timings["total"] = time.perf_counter() - t_start
        extra.update(best_epoch=result.best_epoch, selection=result.selection, start=start.summary(),
                     stopped=result.stopped, derived=result.derived, device=device, processes=sess.dist.world)
        return write_common(out, cfg, inputs, prep, result.poses, "dm2 refine", timings, extra, result.history,
                            sampler=sampler, start=start.poses)
