"""The summary ``dm2 refine``, ``dm2 baseline`` and ``dm2 demo`` print after a run."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.evaluation.consistency_profile import flag_text
from dm2_backend.evaluation.kitti_odometry import result_line
from dm2_backend.pipeline.run_report import RunReport


def print_summary(report: RunReport, out: Path) -> None:
    before, after = report.warm_start_metrics, report.metrics
    for key in after:
        if key in before and key != "error":
            click.echo(f"{key:<28} warm start {before[key]:10.4f}  ->  {report.method} {after[key]:10.4f}")
    if "error" in after:
        click.echo(f"evaluation failed: {after['error']}", err=True)
    kitti = report.details.get("kitti_odometry")
    if kitti and kitti["applicable"]:  # a path of 100 m or less has no segment: nothing to say
        click.echo(result_line(kitti["t_err_percent"], kitti["r_err_deg_per_100m"], kitti["segments"]))
    for text in report.cautions or []:
        click.echo(f"caution: {text}")
    if report.details.get("stopped"):
        click.echo(f"warning: {report.details['stopped']}", err=True)
    t = report.timings
    mem = report.peak_rss_mb
    click.echo(f"{report.frames} frames in {t['total']:.1f} s, peak memory {mem:.0f} MiB")
    for stage, profile in (report.details.get("consistency") or {}).items():
        click.echo(f"consistency of the {stage}: {flag_text(profile)}")
    click.echo(f"wrote {out}")
