"""``dm2 info``: what a trajectory, scan source or bag holds."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from dm2_backend.cli.options import (
    depth_scale_option,
    duplicate_times_option,
    intrinsics_option,
    read_options,
    times_option,
    topic_option,
)
from dm2_backend.formats import (
    SCAN_SOURCES,
    TRAJECTORY_FORMATS,
    ReadOptions,
    detect_scan_source,
    detect_trajectory_format,
    open_scans,
    read_trajectory,
)
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import check_kind


def _time_rows(stamps: np.ndarray | None) -> list[tuple[str, str]]:
    if stamps is None or len(stamps) == 0:
        return [("timestamps", "none")]
    rows = [("time span", f"{float(stamps[0])!r} .. {float(stamps[-1])!r} ({stamps[-1] - stamps[0]:.3f} s)")]
    if len(stamps) > 1:
        dt = np.diff(stamps)
        median = float(np.median(dt))
        rate = f"{1.0 / median:.3f} Hz median" if median > 0 else "none (most stamps repeat or step back)"
        rows.append(("rate", f"{rate} (dt {dt.min():.4g} .. {dt.max():.4g} s)"))
    return rows


def trajectory_rows(traj: Trajectory) -> list[tuple[str, str]]:
    return [
        ("poses", str(len(traj))),
        ("planar", "yes (2D)" if traj.planar else "no (3D)"),
        *_time_rows(traj.timestamps),
        ("path length", f"{traj.path_length:.3f} m"),
    ]


def scan_rows(seq: ScanSequence, sample: int = 5) -> list[tuple[str, str]]:
    idx = np.unique(np.linspace(0, len(seq) - 1, min(sample, len(seq))).astype(int))
    counts = [len(seq[int(i)]) for i in idx]
    rows = [
        ("scans", str(len(seq))),
        ("planar", "yes (2D)" if seq.planar else "no (3D)"),
        ("points per scan", f"{min(counts)} .. {max(counts)} (sampled {len(idx)})"),
        *_time_rows(seq.timestamps),
    ]
    for name, traj in seq.trajectories.items():
        rows.append((f"poses '{name}'", f"{len(traj)} ({traj.path_length:.3f} m)"))
    return rows


def relation_rows(path: Path) -> list[tuple[str, str]]:
    """A Freiburg relations file: ``t1 t2 x y z roll pitch yaw`` per line."""
    from dm2_backend.evaluation.relations import load_relations

    rel = load_relations(path)
    dist = np.linalg.norm(rel[:, 2:5], axis=1)
    return [
        ("path", str(path)),
        ("format", "relations — Freiburg benchmark relations (t1 t2 x y z roll pitch yaw)"),
        ("relations", str(len(rel))),
        ("time span", f"{float(rel[:, :2].min())!r} .. {float(rel[:, :2].max())!r}"),
        ("relation length", f"{dist.min():.3f} .. {dist.max():.3f} m (median {np.median(dist):.3f})"),
    ]


#: trajectories a run folder holds, in the order they are listed
RUN_TRAJECTORIES = ("poses_tum.txt", "poses_kitti.txt", "poses.npy", "poses.g2o", "warm_start_tum.txt")


def is_run_folder(path: Path) -> bool:
    """A folder written by ``dm2 refine`` / ``baseline`` (its ``report.json`` beside the run's own record)."""
    return path.is_dir() and (path / "report.json").is_file() and (
        (path / ".dm2-run.json").is_file() or (path / "poses.npy").is_file())


def run_folder_rows(path: Path) -> list[tuple[str, str]]:
    """A run folder: what made it, its frames, metrics and cautions, and the trajectories to give other tools."""
    from dm2_backend.evaluation.run_compare import read_run_report

    report = read_run_report(path)
    rows = [("path", str(path)), ("format", "dm2 run folder (dm2 refine / dm2 baseline)"),
            ("method", str(report.get("method", "-")))]
    for key in ("frames", "nodes"):
        if isinstance(report.get(key), int):
            rows.append((key, str(report[key])))
    for key, value in report.get("metrics", {}).items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            rows.append((f"metric {key}", f"{value:.6g}"))
    rows += [("caution", c) for c in report.get("cautions", []) if isinstance(c, str)]
    present = [name for name in RUN_TRAJECTORIES if (path / name).is_file()]
    if present:
        rows.append(("trajectories", ", ".join(present)))
    rows.append(("next", f"dm2 info {path / (present[0] if present else 'report.json')}; dm2 compare {path} ..."))
    return rows


def _try(detect, path: Path) -> str | None:
    try:
        return detect(path)
    except InputError:
        return None


def describe(path: Path, fmt: str | None, options: ReadOptions) -> list[tuple[str, str]]:
    """Rows of facts about ``path``; raises :class:`InputError` when nothing can read it."""
    if check_kind(path) is None:  # a FIFO, a device or a symlink loop: one line, never opened
        raise InputError(path, "no such file or folder")
    if fmt == "relations" or (fmt is None and path.name.lower().endswith(".relations")):
        return relation_rows(path)
    if fmt is None and is_run_folder(path):
        return run_folder_rows(path)
    traj_fmt = fmt if fmt in TRAJECTORY_FORMATS else (None if fmt else _try(detect_trajectory_format, path))
    scan_fmt = fmt if fmt in SCAN_SOURCES else (None if fmt else _try(detect_scan_source, path))
    if traj_fmt is None and scan_fmt is None:
        if fmt:
            raise InputError(path, f"unknown format {fmt!r}")
        detect_trajectory_format(path)  # raises with the list of choices
    rows: list[tuple[str, str]] = [("path", str(path))]
    spec = TRAJECTORY_FORMATS.get(traj_fmt) or SCAN_SOURCES.get(scan_fmt)
    rows.append(("format", spec.name + " — " + spec.description))
    if spec.describe is not None:
        rows += spec.describe(path)
    needs_topic = spec.describe is not None and options.topic is None and "bag" in spec.name
    if needs_topic:
        return rows
    traj_error: InputError | None = None
    if traj_fmt is not None:
        try:
            rows += trajectory_rows(read_trajectory(path, traj_fmt, options))
        except InputError as err:
            if scan_fmt is None:
                raise
            traj_error = err
    if scan_fmt is not None and (traj_fmt is None or scan_fmt == traj_fmt or options.topic):
        try:
            rows += scan_rows(open_scans(path, scan_fmt, options))
        except InputError:
            if traj_fmt is None:
                raise
            if traj_error is not None:  # neither reader could use it (e.g. an unknown bag topic)
                raise traj_error from None
    return rows


@click.command("info")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--format", "fmt", default=None, help="Format name (see `dm2 info --help`).")
@topic_option
@times_option
@intrinsics_option
@depth_scale_option
@duplicate_times_option
def command(path: Path, fmt, topic, times, intrinsics, depth_scale, duplicate_times) -> None:
    """Show the format, counts, time span, rates and (for bags) topics of PATH."""
    rows = describe(path, fmt, read_options(topic, times, None, intrinsics, depth_scale, duplicate_times))
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        click.echo(f"{key:<{width}}  {value}")
