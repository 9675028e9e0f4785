"""``dm2 view RUN``: a Rerun recording of a run folder (needs the optional rerun-sdk)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from dm2_backend.cli.map import run_scans, run_trajectory, scan_options
from dm2_backend.runtime.errors import InputError

path_type = click.Path(path_type=Path)


def ground_truth(path: Path, fmt: str | None, run: Path, max_diff: float):
    """Ground truth with one pose per pose of the run: by timestamp when both have them, else by index."""
    from dm2_backend.formats import ReadOptions, read_trajectory
    from dm2_backend.kernel.trajectory import associate_by_time

    gt = read_trajectory(path, fmt, ReadOptions())
    traj = run_trajectory(run)
    if traj.timestamps is not None and gt.timestamps is not None:
        i_run, i_gt = associate_by_time(traj.timestamps, gt.timestamps, max_diff)
        if len(i_run) == len(traj):
            return gt.subset(i_gt[np.argsort(i_run)])
    if len(gt) != len(traj):
        raise InputError(path, f"ground truth has {len(gt)} poses for the run's {len(traj)}")
    return gt


def recording(run: Path, rrd: Path, scans, gt) -> dict:
    """Write the recording; a missing rerun-sdk is one line (exit 2) with the install hint."""
    from dm2_backend.maps.octomap_export import MissingExtra
    from dm2_backend.maps.rerun_view import write_recording

    try:
        return write_recording(run, rrd, scans=scans, gt=gt)
    except MissingExtra as exc:
        raise InputError(None, str(exc)) from exc


def check_rerun() -> None:
    """Fail before any work when rerun-sdk is missing: one line with the install hint."""
    from dm2_backend.maps.octomap_export import MissingExtra
    from dm2_backend.maps.rerun_view import require_rerun

    try:
        require_rerun()
    except MissingExtra as exc:
        raise InputError(None, str(exc)) from exc


@click.command("view")
@click.argument("run", type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--out", "-o", "rrd", type=path_type, default=None,
              help="Recording to write [default: RUN/run.rrd]; open it with `rerun FILE.rrd`.")
@click.option("--gt", type=path_type, default=None, help="Ground truth: colours the map by per-frame error.")
@click.option("--gt-format", default=None)
@scan_options
def command(run, rrd, gt, gt_format, **kw) -> None:
    """Write a Rerun recording of the run folder RUN: warm-start and refined trajectories, the map (coloured
    by per-frame error with --gt), accepted and rejected loop closures, the occupancy and M-Net maps, and
    each frame's scan on the `frame` timeline. The scans are optional (else the run's map.ply is shown)."""
    check_rerun()
    rrd = rrd or run / "run.rrd"
    scans = run_scans(run, kw, required=False)
    truth = ground_truth(gt, gt_format, run, kw["max_diff"]) if gt is not None else None
    info = recording(run, rrd, scans, truth)
    note = "" if scans is not None else " (no scans: map.ply shown; give --scans for per-frame scans)"
    click.echo(f"wrote {rrd}: {len(info['entities'])} entities, {info['frames']} frames{note}")
