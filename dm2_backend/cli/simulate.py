"""``dm2 simulate``: a simulated LiDAR (or 2D laser) sequence with ground truth and a drifting warm start."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.cli.suggest import Choice
from dm2_backend.pipeline.run_folder import run_folder


@click.command("simulate")
@click.option("--frames", "-n", type=click.IntRange(min=2), required=True, help="Number of scans.")
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="Folder to write.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Scene, path, noise and drift seed.")
@click.option("--path", "path_kind", type=Choice(["loop", "eight", "walk", "rpy", "across", "hall"]), default=None,
              help="street: laps of a loop or of a figure-eight [default: loop]; room: walk round the table "
                   "looking at the walls, turn the camera in place (rpy) or go round near the walls looking across "
                   "the room (across), or walk a few metres in a large hall, panning across it (hall; a Kinect v1's "
                   "range and quantised depth) [default: walk].")
@click.option("--scene", type=Choice(["street", "corridors", "hospital", "room"]), default="street",
              show_default=True,
              help="street: buildings, walls, poles and cars along a street; corridors: a ring of featureless "
                   "corridors for a front-facing 2D laser (planar; a frame every 0.25 m; --range default 8 m; "
                   "--rate, --seed and the drift options apply, the other path and LiDAR options do not); "
                   "hospital: a CARMEN log like the Freiburg hospital's (ROBOTLASER1, laser 0.22 m ahead, "
                   "interlaced quarter scans, max-range codes, long returns, pauses, drifting odometry; a frame "
                   "every 0.2 m; --seed only); room: a hand-held depth camera (Kinect-like, 30 Hz) in a furnished "
                   "room, written as a 7-Scenes folder (--path, --laps and --seed apply).")
@click.option("--laps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Laps of the path [default: 2; room: one lap per 600 frames (around the table; the hall: 2.5 m "
                   "walked)].")
@click.option("--extent", type=click.FloatRange(min=10), default=40.0, show_default=True,
              help="Half size of the scene (m); the street's radius is 0.7 x extent.")
@click.option("--rate", type=click.FloatRange(min=0, min_open=True), default=10.0, show_default=True,
              help="Scans per second (timestamps).")
@click.option("--planar", is_flag=True, help="A 2D laser scanner (points with z = 0) instead of a 3D LiDAR.")
@click.option("--beams", type=click.IntRange(min=1), default=32, show_default=True,
              help="LiDAR beams (rows).")
@click.option("--columns", type=click.IntRange(min=1), default=None,
              help="Azimuth steps over 360 degrees [default: 720; 360 with --planar].")
@click.option("--fov-up", type=float, default=10.0, show_default=True, help="Upper vertical limit (deg).")
@click.option("--fov-down", type=float, default=-30.0, show_default=True, help="Lower vertical limit (deg).")
@click.option("--range", "max_range", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Maximum range (m) [default: 2 x extent up to 100; 0.9 x extent up to 40 with --planar].")
@click.option("--range-noise", type=click.FloatRange(min=0), default=0.02, show_default=True,
              help="Standard deviation of the range noise (m).")
@click.option("--dropout", type=click.FloatRange(0, 1, max_open=True), default=0.05, show_default=True,
              help="Fraction of returns lost at random.")
@click.option("--height", type=click.FloatRange(min=0), default=None,
              help="Sensor height above the ground (m) [default: 1.8; 0.5 with --planar].")
@click.option("--yaw-bias", type=float, default=None,
              help="Warm-start drift: yaw bias (rad per metre driven) [default: 0.00035; 0.004 for corridors].")
@click.option("--yaw-noise", type=click.FloatRange(min=0), default=None,
              help="Warm-start drift: yaw random walk (rad per sqrt(metre)) [default: 0.001; 0.004 for "
                   "corridors].")
@click.option("--trans-noise", type=click.FloatRange(min=0), default=None,
              help="Warm-start drift: translation noise (fraction of each step) [default: 0.02; 0.03 for "
                   "corridors].")
@click.option("--force", is_flag=True, help="Overwrite a previous simulation in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def command(frames, out, seed, path_kind, scene, laps, extent, rate, planar, beams, columns, fov_up, fov_down,
            max_range, range_noise, dropout, height, yaw_bias, yaw_noise, trans_noise, force, quiet) -> None:
    """Simulate a LiDAR sequence into a KITTI-odometry-style folder (labelled SIMULATED).

    Writes velodyne/NNNNNN.bin, times.txt, poses.txt (ground truth, LiDAR frame), warm_start.txt (a
    drifting odometry to refine, KITTI format), info.json (all settings) and README.txt.
    """
    if scene == "corridors":
        return corridors(frames, out, seed, rate, max_range, yaw_bias, yaw_noise, trans_noise, force)
    if scene == "hospital":
        return hospital(frames, out, seed, force)
    if scene == "room":
        return room(frames, out, seed, path_kind or "walk", laps or frames / 600, force, quiet)
    path_kind, laps = path_kind or "loop", laps or 2.0
    from dm2_backend.simulate.path import PATHS

    if path_kind not in PATHS:
        raise click.BadParameter(f"{path_kind} is a path of --scene room; a street has {' or '.join(PATHS)}",
                                 param_hint="--path")
    from dm2_backend.simulate.lidar import LidarModel
    from dm2_backend.simulate.sequence import SimSettings, generate

    if fov_up < fov_down:
        raise click.BadParameter("must not be below --fov-down", param_hint="--fov-up")
    lidar = LidarModel(
        beams=1 if planar else beams, fov_up_deg=fov_up, fov_down_deg=fov_down,
        columns=columns or (360 if planar else 720),
        max_range=max_range or (min(0.9 * extent, 40.0) if planar else min(2.0 * extent, 100.0)),
        range_noise=range_noise, dropout=dropout,
        height=height if height is not None else (0.5 if planar else 1.8), planar=planar,
    )
    drift = {k: v for k, v in (("yaw_bias", yaw_bias), ("yaw_sigma", yaw_noise), ("trans_sigma", trans_noise))
             if v is not None}  # the rest: SimSettings' defaults
    settings = SimSettings(frames=frames, seed=seed, extent=extent, laps=laps, path=path_kind, rate_hz=rate,
                           planar=planar, lidar=lidar, **drift)
    kind = "planar laser" if planar else f"{beams}-beam LiDAR"
    with run_folder(out, "simulate", force=force):
        click.echo(f"simulating {frames} {kind} frames ({laps:g} laps of a {path_kind}, seed {seed}) into {out}")
        info = generate(settings, out, progress=not quiet)
    ate = info["warm_start"]["ate_rmse_m"]
    click.echo(f"{info['frames']} frames, {info['points_per_frame']['mean']:.0f} points per frame, "
               f"{info['path_length_m']:.0f} m path; warm start ATE {ate:.2f} m; {info['seconds']:.1f} s")
    click.echo(f"wrote {out} (SIMULATED; see README.txt)")


def corridors(frames, out, seed, rate, max_range, yaw_bias, yaw_noise, trans_noise, force) -> None:
    """``--scene corridors``: the corridor ring of :mod:`dm2_backend.simulate.corridor`."""
    from dm2_backend.simulate.corridor import write_corridors

    drift = {k: v for k, v in (("yaw_bias", yaw_bias), ("yaw_noise", yaw_noise), ("trans_noise", trans_noise))
             if v is not None}
    with run_folder(out, "simulate", force=force):
        click.echo(f"simulating {frames} planar laser frames in a ring of corridors (seed {seed}) into {out}")
        info = write_corridors(out, frames, seed, rate, max_range or 8.0, **drift)
    click.echo(f"{frames} frames, {info['points_per_frame']['mean']:.0f} points per frame, "
               f"{info['path_length_m']:.0f} m path; odometry off by up to "
               f"{info['warm_start']['max_position_error_m']:.2f} m; {info['seconds']:.1f} s")
    click.echo(f"wrote {out} (SIMULATED; see README.txt)")


def hospital(frames, out, seed, force) -> None:
    """``--scene hospital``: the hospital-like CARMEN log of :mod:`dm2_backend.simulate.hospital`."""
    from dm2_backend.simulate.hospital import HospitalSettings, write_hospital

    with run_folder(out, "simulate", force=force):
        click.echo(f"simulating a hospital-like CARMEN log of {frames} scans (seed {seed}) into {out}")
        info = write_hospital(out, HospitalSettings(frames=frames, seed=seed))
    click.echo(f"{frames} scans, {info['path_length_m']:.0f} m path; odometry off by up to "
               f"{info['odometry']['max_position_error_m']:.2f} m")
    click.echo(f"wrote {out} (SIMULATED): hospital.clf, truth.tum, hospital.relations; refine it with "
               f"dm2 refine --scans {out}/hospital.clf --relations {out}/hospital.relations --gt {out}/truth.tum")


def room(frames, out, seed, path_kind, laps, force, quiet) -> None:
    """``--scene room``: the hand-held depth camera of :mod:`dm2_backend.simulate.depth_room`."""
    from dm2_backend.simulate.depth_room import PATHS, write_depth_room

    if path_kind not in PATHS:
        raise click.BadParameter(f"{path_kind} is a street's path; a room has {', '.join(PATHS)}",
                                 param_hint="--path")
    with run_folder(out, "simulate", force=force):
        click.echo(f"simulating {frames} depth frames in a room ({path_kind}, seed {seed}) into {out}")
        info = write_depth_room(out, frames, path_kind, laps, seed, progress=not quiet)
    click.echo(f"{frames} frames, {100 * info['valid_pixels']:.0f} % valid pixels, {info['path_length_m']:.1f} m "
               f"path, {info['median_turn_deg']:.2f} deg a frame; warm start ATE {info['warm_start']['ate_rmse_m']:.3f}"
               f" m; {info['seconds']:.1f} s")
    click.echo(f"wrote {out} (SIMULATED): refine it with dm2 refine --scans {out} --poses {out}/warm_start.tum "
               f"--gt {out}/truth.tum")
