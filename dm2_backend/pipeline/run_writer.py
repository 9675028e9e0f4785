"""The run folder that ``refine`` and ``baseline`` both write: trajectories in several formats (in the input's
frame), the maps, the DeepMapping2 priors, plots, ``config.yaml`` / ``resolved.yaml`` and ``report.json``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dm2_backend import config
from dm2_backend.config.schema import RunConfig
from dm2_backend.evaluation import plots
from dm2_backend.evaluation.consistency_profile import consistency_profiles, write_profiles
from dm2_backend.evaluation.evaluate import EvalOptions, evaluate
from dm2_backend.evaluation.kitti_odometry import KittiOdometryError
from dm2_backend.evaluation.map_quality import MapSampler
from dm2_backend.evaluation.paper_ate import paper_ate
from dm2_backend.evaluation.report import estimate_cautions, run_metrics
from dm2_backend.formats.kitti import read_calib_tr
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.maps.run_maps import write_run_maps
from dm2_backend.optim.epoch import Epoch
from dm2_backend.pipeline import outputs
from dm2_backend.pipeline.full_rate import corrected_full_rate
from dm2_backend.pipeline.inputs import RunInputs, depth_sensor
from dm2_backend.pipeline.run_report import PrepareSummary, RunReport
from dm2_backend.prepare.steps import Prepared
from dm2_backend.runtime import cluster
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.memory import peak_rss_mb, release_mapped
from dm2_backend.runtime.stage_log import StageLog

log = logging.getLogger(__name__)


def metrics_of(traj: Trajectory, inputs: RunInputs) -> dict[str, float]:
    """Accuracy of ``traj`` against the ground truth / relations given to the run (empty without). An
    evaluation that fails is recorded as ``{"error": ...}`` so the run's outputs are still written."""
    return evaluation_of(traj, inputs)[0]


def evaluation_of(traj: Trajectory, inputs: RunInputs) -> tuple[dict[str, float], list[str]]:
    """:func:`metrics_of` and the cautions on those metrics (an ill-posed rotation APE, the standing-still
    reference; see ``evaluation/cautions.py``)."""
    return run_evaluation(traj, inputs)[:2]


def run_evaluation(traj: Trajectory, inputs: RunInputs
                   ) -> tuple[dict[str, float], list[str], KittiOdometryError | None]:
    """:func:`evaluation_of` and the KITTI odometry metric (None without ground truth). A KITTI ground truth
    read with its calibration is in the LiDAR frame: the metric takes both back to the camera frame, as the
    KITTI devkit evaluates."""
    try:
        # the run's ground truth is already one pose per scan (or per listed scan): paired by index
        est = evaluate(traj, gt=inputs.gt, relations=inputs.relations, gt_frames=inputs.gt_frames,
                       options=EvalOptions(by_index=True), kitti_frame=_camera_frame(inputs.gt))
    except InputError as exc:
        log.warning("evaluation failed: %s", exc.message)
        return {"error": exc.message}, [], None
    return run_metrics(est), estimate_cautions(est), est.kitti


def _camera_frame(gt: Trajectory | None) -> np.ndarray | None:
    """KITTI's ``Tr`` (LiDAR to camera) where the ground truth was read with a KITTI odometry ``calib.txt``; None
    otherwise (a KITTI raw drive's calibration holds no camera: its poses stay in the LiDAR frame)."""
    calib = gt.meta.get("calib") if gt is not None else None
    if not calib:
        return None
    try:
        return read_calib_tr(calib)
    except InputError:
        return None


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


def guard_marks(details: dict) -> dict[str, list[int]]:
    """The step guard's held and contradicted steps of a refine (``details["start"]["dense"]``), else none."""
    guard = ((details.get("start") or {}).get("dense") or {}).get("step_guard")
    if not guard:
        return {}
    return {"held": list(guard["held"]), "contradicted": list(guard["check"]["contradicted"])}


def sensor_comment(sensor: dict | None) -> str:
    """The depth camera as YAML comments for ``config.yaml`` (read options, not config: given on the command line)."""
    if sensor is None:
        return ""
    k = sensor["intrinsics"]
    return (f"# depth camera as read (--intrinsics, --depth-scale): fx {k['fx']:g} fy {k['fy']:g} cx {k['cx']:g} "
            f"cy {k['cy']:g} ({sensor['from']['intrinsics']}); depth scale {sensor['depth_scale']:g} units per metre "
            f"({sensor['from']['depth_scale']}); stride {sensor['stride']}\n"
            + (f"# {sensor['image_noise_line']}\n" if sensor.get("image_noise_line") else "")
            + ("# depth smoothed by the noise measured (--smooth-depth)\n" if sensor.get("smoothed") else ""))


def write_run(out: Path, cfg: RunConfig, inputs: RunInputs, prep: Prepared, final: np.ndarray, method: str,
              stages: StageLog, details: dict | None = None, epochs: tuple[Epoch, ...] | None = None,
              sampler: MapSampler | None = None, start: np.ndarray | None = None,
              files: list[str] | None = None, *, started: float) -> RunReport:
    """The run folder of ``refine`` and ``baseline``: trajectories, maps, priors, plots and ``report.json``
    (written once). ``stages``: the run's stages so far (the outputs' are added); ``details``: the method's own
    report entries; ``sampler``: the scans prepared for the map metrics (made here when None); ``start``: where
    the optimiser started; ``files``: files the method wrote; ``started``: when the command started
    (``time.perf_counter``): ``timings["total"]`` runs from it to the report, reading the inputs and writing this
    folder included."""
    out.mkdir(parents=True, exist_ok=True)
    poses_of = {"warm_start": prep.warm_start, "loop_closed": prep.topology.poses, "start": start, "final": final}
    if sampler is None:
        with stages.stage("map_sampler"):
            sampler = map_sampler(inputs)
    with stages.stage("map_metrics"):
        maps = {name: map_metrics(sampler, poses) for name, poses in poses_of.items() if poses is not None}
    sensor = depth_sensor(inputs.scans)
    config.dump(cfg, out / "config.yaml", footer=sensor_comment(sensor))
    # the plugins as run: ``auto`` resolved
    config.dump({name: section.model_dump() for name, section in prep.resolved.items()}, out / "resolved.yaml")
    details = dict(details or {})
    if sensor is not None:
        details["sensor"] = sensor
    if inputs.given is not None and "interpolated_gaps" in inputs.given.meta:  # scan poses bridged across gaps
        details["interpolated_gaps"] = inputs.given.meta["interpolated_gaps"]
    trajectories = {name: None if poses is None else trajectory_of(poses, inputs) for name, poses in poses_of.items()}
    with stages.stage("trajectories_and_plots"):
        written = _write_trajectories_and_plots(out, inputs, prep, trajectories, method, details)
    release_mapped(prep.frames.points)  # the profiles read the scans, not the frames
    with stages.stage("consistency"):
        profiles = consistency_profiles(inputs.scans, {"warm start": prep.warm_start, method: final},
                                        output_timestamps(inputs), prep.frames.planar, folder=_cells_folder(prep))
        written += write_profiles(out, profiles, {"warm start": prep.warm_start[:, :3, 3], method: final[:, :3, 3]},
                                  steps=guard_marks(details))
    log.info("consistency: %s", "; ".join(f"{name} {len(p.segments)} flagged stretch(es), {int(p.flagged.sum())} "
                                          f"frames" for name, p in profiles.items()))
    with stages.stage("maps"):  # after the profiles: each stage's memory peaks alone, not on the other's leftovers
        outputs.write_map(out / "map.ply", prep.frames, final, 2 * (prep.frames.scale.spacing or 0.0))
        written += write_run_maps(out, inputs.scans, final, prep.frames.planar)  # map.pgm/.yaml, octomap.bt, M-Net
    if prep.warm_report:  # e.g. the icp warm start's source of every step (scan match or odometry) and why
        outputs.write_report(out / "warm_start.json", prep.warm_report)
        written.append("warm_start.json")
        details["warm_start"] = _warm_summary(prep.warm_report)
    details["consistency"] = {name: p.summary() for name, p in profiles.items()}
    with stages.stage("evaluation"):
        final_metrics, cautions, kitti = run_evaluation(trajectories["final"], inputs)
        if kitti is not None:
            details["kitti_odometry"] = kitti.as_dict()
        metrics = {name: None if traj is None else {**metrics_of(traj, inputs), **maps[name]}
                   for name, traj in trajectories.items() if name != "final"}
    timings = {**stages.seconds, "total": time.perf_counter() - started}
    report = RunReport(
        method=method,
        frames=len(prep.frames),
        planar=prep.frames.planar,
        ground_truth_scans=len(inputs.gt) if inputs.gt is not None else None,
        metrics={**final_metrics, **maps["final"]},
        cautions=cautions or None,
        warm_start_metrics=metrics["warm_start"],
        loop_closed_metrics=metrics["loop_closed"],
        start_metrics=metrics["start"],
        map_quality=sampler.settings_summary(),
        timings=timings,
        peak_rss_mb=peak_rss_mb(),
        peak_rss_mb_by_stage=dict(stages.peak_mb),
        prepare=PrepareSummary.of(prep),
        files=written + list(files or []),
        epochs=None if epochs is None else [e.row() for e in epochs],
        details=details,
    )
    if epochs is not None:
        plots.plot_run_epochs(out / "epochs.png", report.to_dict())  # from the start (epoch 0) on
    report.write(out / "report.json")
    return report


def _write_trajectories_and_plots(out: Path, inputs: RunInputs, prep: Prepared, trajectories: dict[str, Trajectory],
                                  method: str, details: dict) -> list[str]:
    """The result's and the warm start's trajectories (``trajectories["final"]``, ``["warm_start"]``; and the
    input's full rate, corrected, its summary into ``details``), the priors, the trajectory plots and the
    topology; returns the files written."""
    final = trajectories["final"].poses
    written = outputs.write_trajectories(out, trajectories["final"], inputs.given_path, inputs.given_format)
    written += outputs.write_trajectories(out, trajectories["warm_start"], None, None, stem="warm_start")
    written += outputs.write_layout(out, trajectories["final"], inputs.scans)  # HBA's hba/pose.json
    if inputs.given_full is not None:  # the input trajectory at its own rate, corrected
        full_rate = corrected_full_rate(inputs.given_full, inputs.given, final)
        written += outputs.write_trajectories(out, full_rate.trajectory, inputs.given_path, inputs.given_format,
                                              stem="poses_full_rate")
        log.info("full rate: %d input poses corrected (poses_full_rate_*), %d outside the scans' span keep the "
                 "nearest scan's correction", len(full_rate.trajectory), full_rate.outside)
        details["full_rate"] = full_rate.summary()
    outputs.write_prior_files(out / "prior", prep.warm_start, prep.topology, prep.pairwise)
    per_frame = None
    if inputs.gt is not None:
        per_frame = {"translation error": (paper_ate(inputs.gt.poses, inputs.at_gt(final)).trans_errors, "m")}
    drawn = {"warm start": inputs.at_gt(prep.warm_start), method: inputs.at_gt(final)}  # where gt is known
    outputs.write_plots(out, drawn, inputs.gt, per_frame, None)
    return written + outputs.write_topology(out, prep.topology, final)


def _warm_summary(warm_report: dict) -> dict:
    """The warm start's report for ``report.json``: without the per-step record, and of the per-window verdicts
    (``warm_start.json`` holds them all) the windows taken from the odometry."""
    out = {k: v for k, v in warm_report.items() if k not in ("per_step", "windows")}
    if "windows" in warm_report:
        out["windows_from_odometry"] = [w for w in warm_report["windows"] if w.get("source") == "odometry"]
        out["windows_checked"] = len(warm_report["windows"])
    return out


def _cells_folder(prep: Prepared) -> Path | None:
    """Where a long sequence's profile cells are kept: on a cluster beside the cached frames (the workers read
    both from there: the storage they share), else the system's temporary folder."""
    if cluster.current() is None or prep.frames.stored is None:
        return None
    return prep.frames.stored.parent / "profile-cells"
