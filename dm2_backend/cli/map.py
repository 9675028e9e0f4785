"""``dm2 map RUN``: (re)build the maps of an existing run folder from its scans at the run's final poses."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.cli.options import (
    calib_option,
    depth_scale_option,
    intrinsics_option,
    read_options,
    smooth_depth_option,
    times_option,
    topic_option,
)
from dm2_backend.runtime.errors import InputError

path_type = click.Path(path_type=Path)


def scan_options(f):
    """``--scans`` and how to read them (as given to the run)."""
    decorators = [
        click.option("--scans", "-s", type=path_type, default=None,
                     help="The run's scan source [default: the one recorded in RUN/maps.json]."),
        click.option("--format", "scans_format", default=None, help="Scan source format (else detected)."),
        click.option("--max-diff", type=float, default=0.01, show_default=True,
                     help="Seconds allowed between a scan and the run's pose when matching by time."),
        topic_option, times_option, calib_option, intrinsics_option, depth_scale_option, smooth_depth_option,
    ]
    for d in reversed(decorators):
        f = d(f)
    return f


def run_trajectory(run: Path):
    """The run's final poses (``poses.npy``) with the timestamps of ``poses_tum.txt`` when it has one."""
    from dm2_backend.formats import read_trajectory
    from dm2_backend.formats.poses_npy import read_poses_npy
    from dm2_backend.kernel.trajectory import Trajectory

    if not (run / "poses.npy").exists():
        raise InputError(run, "not a dm2 run folder (no poses.npy)")
    poses = read_poses_npy(run / "poses.npy").poses  # input like any other: bounded, rigid, finite
    stamps = None
    if (run / "poses_tum.txt").exists():
        tum = read_trajectory(run / "poses_tum.txt", "tum")
        stamps = tum.timestamps if len(tum) == len(poses) else None
    return Trajectory(poses, stamps)


def run_scans(run: Path, kw: dict, required: bool = True):
    """The run's scans, one per pose of the run (matched by time, else by index); None when not ``required``
    and no scan source is given or recorded."""
    from dm2_backend.formats import open_scans
    from dm2_backend.kernel.scans import associate_scans
    from dm2_backend.maps.run_maps import read_summary

    path, fmt, smooth = kw["scans"], kw["scans_format"], kw["smooth_depth"]
    if path is None:  # the recorded source, read as the run read it
        recorded = read_summary(run).get("scans")
        recorded = recorded if isinstance(recorded, dict) else {}
        smooth = smooth or recorded.get("smoothed") is True
        src = recorded.get("source")
        if not src or not Path(src).exists():
            if not required:
                return None
            why = f"recorded {src} no longer exists" if src else "no scan source recorded in maps.json"
            raise InputError(run, f"{why}: give --scans")
        path, fmt = Path(src), fmt or recorded.get("format")
    options = read_options(kw["topic"], kw["times"], kw["calib"], kw["intrinsics"], kw["depth_scale"],
                           smooth_depth=smooth)
    scans = open_scans(path, fmt, options)
    traj = run_trajectory(run)
    scans, matched = associate_scans(scans, traj, kw["max_diff"])
    if len(matched) != len(traj):
        raise InputError(path, f"only {len(matched)} of the run's {len(traj)} poses have a scan")
    from dm2_backend.pipeline.inputs import looks_planar

    report = _report(run)
    scans.planar = bool(report["planar"]) if "planar" in report else looks_planar(scans, None)
    return scans


def _report(run: Path) -> dict:
    import json

    try:
        return json.loads((run / "report.json").read_text())
    except (OSError, ValueError):
        return {}


@click.command("map")
@click.argument("run", type=click.Path(path_type=Path, exists=True, file_okay=False))
@scan_options
@click.option("--quiet", "-q", is_flag=True, help="No progress lines.")
def command(run, quiet, **kw) -> None:
    """Write the maps of the run folder RUN: map.pgm/map.yaml (planar: ROS map_server occupancy grid by ray
    casting), mnet_map.pgm/.yaml (the trained M-Net on the same cells), octomap.bt (3D, needs pyoctomap) and
    mnet_mesh.ply (3D: the M-Net's decision surface, needs scikit-image), and maps.json."""
    from dm2_backend.maps.run_maps import write_run_maps
    from dm2_backend.pipeline.run_folder import adding_to

    scans = run_scans(run, kw)
    traj = run_trajectory(run)
    echo = None if quiet else (lambda msg: click.echo(msg, err=True))
    with adding_to(run):
        files = write_run_maps(run, scans, traj.poses, scans.planar, progress=not quiet, strict=True, echo=echo)
    click.echo(f"wrote {', '.join(files)} in {run}")
