"""Run reports (``<run folder>/report.json``) read back and set side by side (``dm2 compare``).

Run report schema (``<run folder>/report.json``, one JSON object)::

    method       str               what produced the run, e.g. "dm2 refine" or "KISS-ICP warm start"
    metrics      {name: number}    flat metrics, units in the names (see :func:`.report.run_metrics`), e.g.
                                   "ape_trans_rmse_m", "ape_rot_rmse_deg", "relations_trans_mean_m"
    timings      {stage: seconds}  wall-clock seconds per stage, e.g. {"prepare": 12.1, "refine": 340.2}
    peak_rss_mb  number            peak resident memory of the run, MiB
    cautions     [str]             optional: where the metrics are ill-posed (a rotation APE the alignment
                                   does not determine) or a trajectory standing still scores within reach
    epochs       [ {...} ]         optional, per refinement epoch: "epoch" (int), "loss" and "ate" (numbers),
                                   each key optional; "ate" may also be {name: number}; "ate_metric"
                                   names the metric "ate" is (a key of "metrics": "ape_trans_rmse_m" or
                                   "relations_trans_mean_m"; its value at the start is in "start_metrics")
"""

from __future__ import annotations

import json
from pathlib import Path

from dm2_backend.evaluation.text_table import format_table
from dm2_backend.runtime.errors import InputError


def read_run_report(path: str | Path) -> dict:
    """A run report (a folder holding ``report.json``, or the file); types are checked."""
    path = Path(path)
    file = path / "report.json" if path.is_dir() else path
    if not file.is_file():
        raise InputError(file, "no such run report")
    try:
        data = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(file, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(file, "a run report is a JSON object")
    for key in ("metrics", "timings"):
        if not isinstance(data.get(key, {}), dict):
            raise InputError(file, f"'{key}' must be an object of name: number")
    if "epochs" in data and not isinstance(data["epochs"], list):
        raise InputError(file, "'epochs' must be a list")
    return data


def compare_table(reports: dict[str, dict]) -> str:
    """One table, a column per run and a row per method / metric / timing / memory."""
    runs = list(reports)
    metric_keys = list(dict.fromkeys(k for r in reports.values() for k in r.get("metrics", {})))
    stage_keys = list(dict.fromkeys(k for r in reports.values() for k in r.get("timings", {})))
    body: list[list] = [["method", *(str(reports[r].get("method", "-")) for r in runs)]]
    for k in metric_keys:
        body.append([k, *(_as_number(reports[r].get("metrics", {}).get(k)) for r in runs)])
    for k in stage_keys:
        body.append([f"time {k} [s]", *(_as_number(reports[r].get("timings", {}).get(k)) for r in runs)])
    if stage_keys and "total" not in stage_keys:  # a run's own total counts the stages once, with start-up
        totals = []
        for r in runs:
            vals = [_as_number(v) for v in reports[r].get("timings", {}).values()]
            nums = [v for v in vals if isinstance(v, float)]
            totals.append(sum(nums) if nums else None)
        body.append(["time total [s]", *totals])
    if any(any(r.get("prepare", {}).get("cached", {}).values()) for r in reports.values()):
        body.append(["preparation cached", *(_cached(reports[r]) for r in runs)])
    body.append(["peak RSS [MB]", *(_as_number(reports[r].get("peak_rss_mb")) for r in runs)])
    notes = [f"{r}: caution: {text}" for r in runs for text in _texts(reports[r].get("cautions"))]
    return "\n".join([format_table(["quantity", *runs], body), *notes])


def _texts(value) -> list[str]:
    """A report's list of strings (anything else in a hand-edited file is left out)."""
    return [v for v in value if isinstance(v, str)] if isinstance(value, list) else []


def _cached(report: dict) -> str:
    """Which preparation steps a run loaded from the cache instead of computing (their time is not in it)."""
    steps = [k for k, v in report.get("prepare", {}).get("cached", {}).items() if v]
    return ",".join(steps) if steps else "no"


def _as_number(v):
    if isinstance(v, bool) or v is None:
        return v
    if isinstance(v, (int, float)):
        return float(v)
    return str(v)
