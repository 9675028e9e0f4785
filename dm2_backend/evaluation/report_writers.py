"""The files of an evaluation (written atomically): JSON, CSV and Markdown, and evo result archives."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

from evo.tools import file_interface

from dm2_backend.evaluation.paper_ate import LABEL as PAPER_LABEL
from dm2_backend.evaluation.report import (
    COLUMNS,
    EvalReport,
    describe,
    display_rows,
    kitti_lines,
    map_line,
    rows,
    to_json,
)
from dm2_backend.evaluation.text_table import fmt
from dm2_backend.runtime.atomic import atomic_write


def write_json(report: EvalReport, path: str | Path) -> None:
    with atomic_write(path) as fh:
        json.dump(to_json(report), fh, indent=2, allow_nan=False)
        fh.write("\n")


def write_csv(report: EvalReport, path: str | Path) -> None:
    with atomic_write(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        writer.writeheader()
        for r in rows(report):
            writer.writerow({k: _csv_cell(r.get(k)) for k in COLUMNS})


def _csv_cell(v):
    return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v


def write_markdown(report: EvalReport, path: str | Path) -> None:
    header, body = display_rows(report)
    lines = ["# Trajectory evaluation", ""]
    if report.ground_truth:
        lines.append(f"Ground truth: `{report.ground_truth}`  ")
    if report.relations_file:
        lines.append(f"Relations: `{report.relations_file}`  ")
    lines += [f"- {line}" for est in report.estimates for line in describe(est)]
    lines += [f"- {line}" for line in map_line(report)]
    lines += ["", "| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(c) for c in r) + " |" for r in body]
    if kitti_lines(report):
        lines += ["", *(f"- {line}" for line in kitti_lines(report))]
    if any(e.paper is not None for e in report.estimates):
        lines += ["", f"*{PAPER_LABEL}*: DeepMapping2's official definition (sqrt of the mean distance after "
                  "rigid alignment; mean absolute yaw error). Not comparable with APE."]
    with atomic_write(path) as fh:
        fh.write("\n".join(lines) + "\n")


def safe_name(label: str) -> str:
    """A file-name part from a label that may come from file content (a topic, a frame id): letters, digits,
    ``. _ -`` only, never starting with a dot (no hidden files, no ``..``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label).strip("._") or "estimate"


def write_evo_results(report: EvalReport, folder: str | Path) -> list[Path]:
    """evo result archives (``evo_res`` reads them), one per estimate and metric."""
    folder = Path(folder)
    written = []
    for est in report.estimates:
        if est.poses is None:
            continue
        for key, m in est.poses.metrics.items():
            path = folder / f"{safe_name(est.label)}_{key}.zip"
            with atomic_write(path, "wb") as fh:
                file_interface.save_res_file(fh, m.result)
            written.append(path)
    return written
