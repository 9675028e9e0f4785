"""Click options shared by several commands."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.cli.suggest import Choice
from dm2_backend.formats import ReadOptions


def read_options(
    topic: str | None = None,
    times: Path | None = None,
    calib: Path | None = None,
    intrinsics: str | None = None,
    depth_scale: float | None = None,
    duplicate_times: str = "keep",
    smooth_depth: bool = False,
) -> ReadOptions:
    fx_fy_cx_cy = None
    if intrinsics:
        try:
            values = tuple(float(v) for v in intrinsics.replace(",", " ").split())
        except ValueError:
            values = ()
        if len(values) != 4:
            raise click.BadParameter("give four numbers: fx fy cx cy", param_hint="--intrinsics")
        fx_fy_cx_cy = values
    return ReadOptions(
        topic=topic, times=times, calib=calib, intrinsics=fx_fy_cx_cy, depth_scale=depth_scale,
        duplicate_times=duplicate_times, smooth_depth=smooth_depth,
    )


existing_path = click.Path(exists=False, path_type=Path)

topic_option = click.option("--topic", "-t", default=None, help="Bag topic (trajectory or scans).")
times_option = click.option("--times", type=existing_path, default=None, help="KITTI times.txt.")
calib_option = click.option(
    "--calib", type=existing_path, default=None,
    help="KITTI calib.txt: KITTI poses are camera-frame and get converted to/from the LiDAR frame.",
)
intrinsics_option = click.option(
    "--intrinsics", default=None, help='Depth camera "fx fy cx cy" (TUM RGB-D layout).'
)
depth_scale_option = click.option(
    "--depth-scale", type=float, default=None,
    help="Depth units per metre [default: 1000 for 7-Scenes, 5000 for TUM RGB-D].",
)
smooth_depth_option = click.option(
    "--smooth-depth", is_flag=True, default=False,
    help="Smooth each depth pixel over its neighbours on the same surface, by the camera's noise measured on its "
         "own images (docs/decisions/0022-depth-smoothing-available-off.md) [default: depth as recorded].",
)
duplicate_times_option = click.option(
    "--duplicate-times", type=Choice(["keep", "keep-first", "error"]), default="keep", show_default=True,
    help="A repeated timestamp in a TUM/EuRoC file or a KITTI times file: keep every pose as evo does (with a "
         "warning), keep the first pose of each, or refuse the file.",
)
