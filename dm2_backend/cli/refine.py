"""``dm2 refine``: refine a SLAM trajectory with DeepMapping2."""

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
    times_option,
    topic_option,
)
from dm2_backend.config_schema import PluginSection, RunConfig
from dm2_backend.errors import InputError
from dm2_backend.formats import detect_trajectory_format
from dm2_backend.formats.kitti import find_calib, looks_camera_frame
from dm2_backend.input_files import check_kind
from dm2_backend.pipeline.inputs import load_inputs
from dm2_backend.pipeline.run_folder import digest, fingerprint, run_folder
from dm2_backend.pipeline.run_report import RunReport
from dm2_backend.prepare.steps import default_cache_dir

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
        topic_option, times_option, calib_option, intrinsics_option, depth_scale_option,
        duplicate_times_option,
    ]
    for d in reversed(decorators):
        f = d(f)
    return f


def default_to_icp(cfg: RunConfig, inputs, asked: bool) -> bool:
    """Whether the run starts from the ``icp`` warm start instead of the default ``poses``: when there is no
    trajectory to refine, or (unless a warm start was ``asked`` for on the command line or in the config) only
    the wheel odometry a 2D laser log carries, which the icp warm start fuses with scan matching."""
    if cfg.warm_start.name != "poses":
        return False
    carried_odometry = inputs.given is not None and inputs.given_path is None and inputs.scans.planar
    return inputs.given is None or (carried_odometry and not asked)


def prepare_run(kw: dict, overrides: dict):
    """Read the inputs and the effective config of a run from the shared options."""
    for name in ("scans", "poses", "gt", "relations", "times", "calib", "config_path"):
        if kw.get(name) is not None:
            check_kind(kw[name])  # a FIFO or a device is refused before anything opens it
    calib = kw["calib"] or kitti_calibration(kw)
    options = read_options(kw["topic"], kw["times"], calib, kw["intrinsics"], kw["depth_scale"],
                           kw["duplicate_times"])
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
    asked = bool(kw["warm_start"]) or config.sets(kw["config_path"], "warm_start")
    if asked and cfg.warm_start.name == "poses" and inputs.given is None:
        source, what = (None, "--warm-start poses") if kw["warm_start"] else (kw["config_path"], "warm_start poses")
        raise InputError(source, f"{what} starts from a given trajectory and there is none: give --poses FILE "
                                 "(or --warm-start icp to compute one from the scans)")
    if default_to_icp(cfg, inputs, asked):  # a validated plugin section (icp takes no options here)
        cfg = cfg.model_copy(update={"warm_start": PluginSection(name="icp")})
    cache = None if kw["no_cache"] else (kw["cache_dir"] or default_cache_dir())
    return inputs, cfg, cache


@click.command("refine")
@run_options
@click.option("--epochs", type=click.IntRange(min=1), default=None, help="Optimisation epochs (at least 1).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="Torch device.")
@click.option("--resume", is_flag=True, help="Continue an interrupted run in --out from its checkpoint.")
@click.option("--nproc", type=click.IntRange(min=1), default=None,
              help="Optimise in N processes (torch.distributed: gloo on CPU, NCCL with one GPU each) "
                   "[default: config nproc, 1]. Under torchrun its processes are the ranks.")
@click.option("--rerun", "rerun_path", type=path_type, default=None,
              help="Also write a Rerun recording of the run (needs rerun-sdk; see `dm2 view`).")
def command(epochs, device, resume, nproc, rerun_path, **kw) -> None:
    """Refine the poses of a scan sequence with DeepMapping2 and write a run folder."""
    from dm2_backend.pipeline.refine import refine

    overrides: dict = {}
    if epochs is not None:
        overrides["optimiser"] = {"epochs": epochs, "max_steps": 0}  # explicit epochs: no step cap
    if device is not None:
        overrides["device"] = device
    if nproc is not None:
        overrides["nproc"] = nproc
    inputs, cfg, cache = prepare_run(kw, overrides)
    check_device(cfg.device)
    if rerun_path is not None:
        from dm2_backend.cli.view import check_rerun, recording

        check_rerun()  # before the run, not after it
    with output_folder(kw, "refine", cfg, inputs, resume):
        report = refine(inputs, cfg, kw["out"], cache, resume=resume, progress=not kw["quiet"],
                        started=command_started())
    if report is not None:  # None: a torchrun rank other than 0
        print_summary(report, kw["out"])
        if rerun_path is not None:
            recording(kw["out"], rerun_path, inputs.scans, inputs.gt)
            click.echo(f"wrote {rerun_path}")


def output_folder(kw: dict, command: str, cfg: RunConfig, inputs, resume: bool = False):
    """The run folder rule (``pipeline/run_folder.py``) for ``--out``; torchrun ranks other than 0 write
    nothing and skip it."""
    if int(os.environ.get("RANK", "0")) != 0:
        return contextlib.nullcontext()
    fp = fingerprint(cfg, command=command, scans=kw["scans"] and Path(kw["scans"]).resolve(),
                     frames=len(inputs.scans), poses=kw["poses"] and Path(kw["poses"]).resolve(),
                     poses_content=digest(kw["poses"]))
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


def check_device(device: str) -> None:
    """``cuda`` without a usable CUDA device is an input error before any work (not an assertion inside torch
    after the preparation)."""
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise InputError(None, "--device cuda: no CUDA device is available to this torch build "
                                   f"(torch {torch.__version__}); use --device auto or cpu")


def print_summary(report: RunReport, out: Path) -> None:
    before, after = report.warm_start_metrics, report.metrics
    for key in after:
        if key in before and key != "error":
            click.echo(f"{key:<28} warm start {before[key]:10.4f}  ->  {report.method} {after[key]:10.4f}")
    if "error" in after:
        click.echo(f"evaluation failed: {after['error']}", err=True)
    for text in report.cautions or []:
        click.echo(f"caution: {text}")
    if report.details.get("stopped"):
        click.echo(f"warning: {report.details['stopped']}", err=True)
    t = report.timings
    mem = report.peak_rss_mb
    click.echo(f"{report.frames} frames in {t['total']:.1f} s, peak memory {mem:.0f} MiB")
    for stage, profile in (report.details.get("consistency") or {}).items():
        stretches = ", ".join(f"{s['first']}-{s['last']}" for s in profile["segments"]) or "none"
        level = "no frame scored" if profile["level_m"] is None else f"frames agree to {profile['level_m']:.3g} m"
        caution = " (planar scans: the profile is validated on 3D data only)" if report.planar else ""
        click.echo(f"consistency of the {stage}: {level}; flagged frames: {stretches}{caution}")
    click.echo(f"wrote {out}")
