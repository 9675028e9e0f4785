"""What ``dm2 refine`` and ``dm2 baseline`` share: their options (inputs, config, plugins, cache), reading the
inputs and the effective config (with the KITTI calibration found beside the inputs), the run folder rule."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import click

from dm2_backend import config
from dm2_backend.cli.options import (
    calib_option,
    depth_scale_option,
    duplicate_times_option,
    intrinsics_option,
    read_options,
    smooth_depth_option,
    times_option,
    topic_option,
)
from dm2_backend.config.schema import RunConfig
from dm2_backend.formats import detect_trajectory_format
from dm2_backend.formats.kitti import find_calib, looks_camera_frame
from dm2_backend.pipeline.inputs import load_inputs, with_warm_start
from dm2_backend.pipeline.run_folder import digest, fingerprint, refuse_overlap, run_folder
from dm2_backend.prepare.steps import default_cache_dir
from dm2_backend.runtime.cluster import ClusterSpec
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import check_kind

path_type = click.Path(path_type=Path)


def run_options(f=None, *, scans_required: bool = True):
    """Options shared by ``refine`` and ``baseline``: inputs, config, plugins, cache."""
    if f is None:
        return lambda g: run_options(g, scans_required=scans_required)
    decorators = [
        click.option("--scans", "-s", type=path_type, required=scans_required,
                     help="Scan source: folder, bag (+ --topic), CARMEN log, depth sequence."),
        click.option("--poses", "-p", type=path_type, default=None,
                     help="Trajectory to refine (any format); optional when a warm-start plugin computes one "
                          "or the scan source carries odometry."),
        click.option("--out", "-o", type=path_type, required=True, help="Run folder to write."),
        click.option("--force", is_flag=True,
                     help="Write into a non-empty --out (a previous run's files there are replaced)."),
        click.option("--format", "scans_format", default=None, help="Scan source format (else detected)."),
        click.option("--poses-format", default=None, help="Trajectory format (detected otherwise)."),
        click.option("--config", "-c", "config_path", type=path_type, default=None, help="YAML config."),
        click.option("--gt", type=path_type, default=None, help="Ground truth: live ATE and metrics."),
        click.option("--gt-format", default=None),
        click.option("--relations", type=path_type, default=None,
                     help="Freiburg relations file: live relations metric and metrics."),
        click.option("--warm-start", default=None,
                     help="Warm-start plugin (default: poses; icp without --poses, fusing the odometry a 2D "
                          "scan source carries)."),
        click.option("--place-recognition", default=None,
                     help="Place-recognition plugin (default auto: loops for laser scans, loops3d for depth cameras)."),
        click.option("--registration", default=None, help="Pairwise registration plugin (default icp)."),
        click.option("--seed", type=int, default=None, help="Random seed (deterministic runs)."),
        click.option("--cache-dir", type=path_type, default=None,
                     help="Preparation cache (default $DM2_CACHE_DIR or ~/.cache/dm2)."),
        click.option("--no-cache", is_flag=True, help="Recompute the preparation steps."),
        click.option("--max-diff", type=float, default=0.01, show_default=True,
                     help="Seconds allowed between a scan and its pose when associating by time."),
        click.option("--quiet", "-q", is_flag=True, help="No progress bars."),
        click.option("--workers", type=click.IntRange(min=0), default=None,
                     help="Run the preparation's tasks (the registration, loops3d's odometry check) on a local Dask "
                          "cluster of N worker processes; 0: in this process, whatever $DASK_SCHEDULER_ADDRESS says "
                          "[default: in this process]."),
        click.option("--scheduler", default=None,
                     help="Run the preparation's tasks on the Dask cluster whose scheduler is at this address "
                          "(tcp://host:8786; default $DASK_SCHEDULER_ADDRESS). Its workers read the frames from "
                          "the cache folder (put it on storage they share; with --no-cache the frames travel with "
                          "the tasks)."),
        topic_option, times_option, calib_option, intrinsics_option, depth_scale_option, smooth_depth_option,
        duplicate_times_option,
    ]
    for d in reversed(decorators):
        f = d(f)
    return f


def prepare_run(kw: dict, overrides: dict):
    """Read the inputs and the effective config of a run from the shared options."""
    for name in ("scans", "poses", "gt", "relations", "times", "calib", "config_path"):
        if kw.get(name) is not None:
            check_kind(kw[name])  # a FIFO or a device is refused before anything opens it
    cache = None if kw["no_cache"] else (kw["cache_dir"] or default_cache_dir())
    refuse_overlap(kw["out"], {f"--{name.removesuffix('_path')}": kw.get(name) for name in
                               ("scans", "poses", "gt", "relations", "times", "calib", "config_path")}
                   | {"--cache-dir": cache})
    calib = kw["calib"] or kitti_calibration(kw)
    options = read_options(kw["topic"], kw["times"], calib, kw["intrinsics"], kw["depth_scale"],
                           kw["duplicate_times"], kw["smooth_depth"])
    inputs = load_inputs(kw["scans"], kw["scans_format"], kw["poses"], kw["poses_format"], options,
                         kw["gt"], kw["gt_format"], kw["relations"], kw["max_diff"])
    if calib is None and not inputs.scans.planar:
        warn_camera_frame(kw, inputs)
    for key, section in (("warm_start", "warm_start"), ("place_recognition", "place_recognition"),
                         ("registration", "registration")):
        if kw[key]:
            overrides[section] = {"name": kw[key]}
    if kw["seed"] is not None:
        overrides["seed"] = kw["seed"]
    cfg = config.load(kw["config_path"], overrides)
    asked = None if not kw["warm_start"] and not config.sets(kw["config_path"], "warm_start") else (
        "--warm-start" if kw["warm_start"] else kw["config_path"])
    return inputs, with_warm_start(cfg, inputs, asked), cache


def cluster_of(kw: dict) -> ClusterSpec:
    """Where the preparation's tasks run (``--workers`` / ``--scheduler``)."""
    return ClusterSpec.of(kw["workers"], kw["scheduler"])


def output_folder(kw: dict, command: str, cfg: RunConfig, inputs, resume: bool = False):
    """The run folder rule (``pipeline/run_folder.py``) for ``--out``; torchrun ranks other than 0 write
    nothing and skip it."""
    if int(os.environ.get("RANK", "0")) != 0:
        return contextlib.nullcontext()
    fp = fingerprint(cfg, command=command, scans=kw["scans"] and Path(kw["scans"]).resolve(),
                     frames=len(inputs.scans), poses=inputs.given_path and Path(inputs.given_path).resolve(),
                     poses_content=digest(inputs.given_path))  # --poses, or the poses file of the scans' layout
    return run_folder(kw["out"], command, force=kw["force"], resume=resume, fp=fp)


def _kitti_files(kw: dict) -> list[tuple[str, Path]]:
    """The --poses / --gt files that are KITTI poses (given or detected format)."""
    found = []
    for opt, fmt in (("poses", kw["poses_format"]), ("gt", kw["gt_format"])):
        path = kw[opt]
        if path is None:
            continue
        try:
            fmt = fmt or detect_trajectory_format(path)
        except InputError:
            continue  # the reader says what is wrong with it
        if fmt == "kitti":
            found.append((opt, Path(path)))
    return found


def kitti_calibration(kw: dict) -> Path | None:
    """``calib.txt`` beside KITTI poses or the scans, announced, when no --calib is given."""
    files = _kitti_files(kw)
    if not files:
        return None
    calib = find_calib(*(path for _, path in files), kw["scans"])
    if calib is not None:
        click.echo(f"using {calib} (found beside the inputs): KITTI poses are camera frame and are converted to "
                   "the LiDAR frame; outputs are written in the camera frame, LiDAR-frame copies as *_lidar_*",
                   err=True)
    return calib


def warn_camera_frame(kw: dict, inputs) -> None:
    """A warning when KITTI poses without calibration look like camera-frame poses applied to LiDAR scans."""
    trajectories = {"poses": inputs.given, "gt": inputs.gt}
    for opt, path in _kitti_files(kw):
        traj = trajectories[opt]
        if traj is not None and looks_camera_frame(traj.poses):
            click.echo(f"warning: {path}: these KITTI poses look camera-frame (y down, z forward) but no calib.txt "
                       "was given or found: they are used as LiDAR poses; give --calib calib.txt", err=True)


def command_started() -> float | None:
    """When the ``dm2`` command started (``time.perf_counter``), for a run's total time; None outside one."""
    ctx = click.get_current_context(silent=True)
    obj = ctx.find_root().obj if ctx is not None else None
    return obj.get("started") if isinstance(obj, dict) else None
