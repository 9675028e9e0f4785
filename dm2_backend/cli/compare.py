"""``dm2 compare``: one table of several runs' ``report.json`` (method, metrics, timings, peak memory)."""

from __future__ import annotations

from pathlib import Path

import click

from dm2_backend.evaluation.run_compare import compare_table, read_run_report


@click.command("compare")
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
def command(runs: tuple[Path, ...]) -> None:
    """Compare run folders (each holding a report.json, see dm2_backend/evaluation/run_compare.py)."""
    reports: dict[str, dict] = {}
    for path in runs:
        name = (path.parent.name if path.is_file() else path.name) or str(path)
        while name in reports:
            name = f"{name}#{len(reports) + 1}"
        reports[name] = read_run_report(path)
    click.echo(compare_table(reports))
