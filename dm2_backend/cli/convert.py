"""``dm2 convert``: any trajectory format to any writable one."""

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
from dm2_backend.formats import format_for_output, read_trajectory, write_trajectory


@click.command("convert")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@click.argument("output_path", metavar="OUTPUT", type=click.Path(path_type=Path))
@click.option("--from", "src_fmt", default=None, help="Input format (detected when unambiguous).")
@click.option("--to", "dst_fmt", default=None, help="Output format (from OUTPUT's suffix otherwise).")
@click.option("--out-topic", default=None, help="Topic to write when OUTPUT is a bag.")
@topic_option
@times_option
@calib_option
@duplicate_times_option
def command(
    input_path, output_path, src_fmt, dst_fmt, out_topic, topic, times, calib, duplicate_times
) -> None:
    """Convert the trajectory in INPUT to OUTPUT."""
    options = read_options(topic, times, calib, duplicate_times=duplicate_times)
    traj = read_trajectory(input_path, src_fmt, options)
    fmt = dst_fmt or format_for_output(output_path)
    out_options = read_options(out_topic or topic, None, calib)
    write_trajectory(traj, output_path, fmt, out_options)
    click.echo(f"wrote {len(traj)} poses to {output_path} ({fmt})")
