"""``dm2 convert``: any trajectory format to any writable one; stamps invented or dropped are announced."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.cli.options import (
    calib_option,
    duplicate_times_option,
    read_options,
    times_option,
    topic_option,
)
from dm2_backend.formats import TRAJECTORY_FORMATS, format_for_output, read_trajectory, write_trajectory
from dm2_backend.formats.kitti import times_for
from dm2_backend.formats.registry import ReadOptions
from dm2_backend.kernel.trajectory import Trajectory

#: formats whose writer puts the stamps in a file of their own (``--out-times``)
TIMES_FILE_FORMATS = ("kitti",)


def with_times(traj: Trajectory, times: Path | None, options: ReadOptions | None = None) -> Trajectory:
    """``traj`` with the stamps of ``times`` (one a line; a repeated one as ``--duplicate-times`` says) when its
    format has none of its own (g2o, .npy); readers that take ``--times`` themselves (KITTI) have used it
    already."""
    if times is None or traj.timestamps is not None:
        return traj
    return times_for(traj, times, options)


def stamps_note(traj: Trajectory, fmt: str, input_path: Path, output_path: Path, out_times: Path | None) -> str | None:
    """One line when the conversion invents or drops timestamps, else None."""
    stamped = TRAJECTORY_FORMATS[fmt].stamped
    if traj.timestamps is None and stamped:
        return (f"note: {input_path} has no timestamps: {output_path} gets the pose index as the time "
                "(0, 1, 2, ... s); give --times FILE for the real ones")
    if traj.timestamps is not None and not stamped and out_times is None:
        keep = "; --out-times FILE writes them" if fmt in TIMES_FILE_FORMATS else ""
        return f"note: {fmt} stores no timestamps: the {len(traj)} stamps of {input_path} are not written{keep}"
    return None


@click.command("convert")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@click.argument("output_path", metavar="OUTPUT", type=click.Path(path_type=Path))
@click.option("--from", "src_fmt", default=None, help="Input format (detected when unambiguous).")
@click.option("--to", "dst_fmt", default=None, help="Output format (from OUTPUT's suffix otherwise).")
@click.option("--out-topic", default=None, help="Topic to write when OUTPUT is a bag.")
@click.option("--out-times", type=click.Path(path_type=Path), default=None,
              help="KITTI output: also write the stamps to this times.txt (one a line).")
@topic_option
@times_option
@calib_option
@duplicate_times_option
def command(
    input_path, output_path, src_fmt, dst_fmt, out_topic, out_times, topic, times, calib, duplicate_times
) -> None:
    """Convert the trajectory in INPUT to OUTPUT. --times gives INPUT's stamps when its format has none."""
    options = read_options(topic, times, calib, duplicate_times=duplicate_times)
    fmt = dst_fmt or format_for_output(output_path)
    if out_times is not None and fmt not in TIMES_FILE_FORMATS:
        raise click.UsageError(f"--out-times is for {', '.join(TIMES_FILE_FORMATS)} output, not {fmt}")
    traj = with_times(read_trajectory(input_path, src_fmt, options), times, options)
    if fmt in TRAJECTORY_FORMATS:
        note = stamps_note(traj, fmt, input_path, output_path, out_times)
        if note:
            click.echo(note, err=True)
    out_options = read_options(out_topic or topic, out_times, calib)
    write_trajectory(traj, output_path, fmt, out_options)
    click.echo(f"wrote {len(traj)} poses to {output_path} ({fmt})")
