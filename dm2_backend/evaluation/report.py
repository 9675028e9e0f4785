"""Evaluation reports as types: one estimate's and one evaluation's results, their rows, JSON and terminal text,
and a run report's flat metrics. The files are written by :mod:`.report_writers`, ``dm2 compare``'s table of
run reports is :mod:`.run_compare`, the text tables :mod:`.text_table`.

Evaluation JSON (``dm2 eval --json``): ``format`` ("dm2-eval/1"), ``ground_truth``, ``relations``,
``settings`` and ``estimates`` (a list with ``label``, ``path``, ``association``, ``alignment`` and
``metrics``: ``ape_trans``/``ape_rot``/``rpe_trans``/``rpe_rot`` with evo's statistics, ``paper_ate``,
``kitti_odometry`` and ``relations``). CSV and Markdown hold one row per estimate and metric with the columns of
:data:`COLUMNS`; ``value`` is the headline figure of the row (rmse for APE/RPE, mean for relations, the
paper's figure for the paper ATE).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dm2_backend.evaluation.ape_rpe import STAT_KEYS, PoseErrors
from dm2_backend.evaluation.cautions import pose_cautions, standing_still_rmse
from dm2_backend.evaluation.kitti_odometry import KittiOdometryError
from dm2_backend.evaluation.map_quality import MapQuality
from dm2_backend.evaluation.paper_ate import LABEL as PAPER_LABEL
from dm2_backend.evaluation.paper_ate import PaperATE
from dm2_backend.evaluation.relations import RelationsResult
from dm2_backend.evaluation.text_table import format_table

FORMAT = "dm2-eval/1"
COLUMNS = ("estimate", "metric", "unit", "count", "value", *STAT_KEYS)
_LABELS = {
    "ape_trans": "APE trans",
    "ape_rot": "APE rot",
    "rpe_trans": "RPE trans",
    "rpe_rot": "RPE rot",
    "paper_ate_trans": f"{PAPER_LABEL} trans",
    "paper_ate_rot": f"{PAPER_LABEL} rot",
    "relations_trans": "relations trans",
    "relations_trans_sq": "relations trans^2",
    "relations_rot": "relations rot",
    "relations_rot_sq": "relations rot^2",
    "map_entropy": "map entropy",
    "map_plane_variance": "map plane variance",
}


@dataclass
class EstimateReport:
    """Everything computed for one estimate."""

    label: str
    path: str
    poses: PoseErrors | None = None
    paper: PaperATE | None = None
    relations: RelationsResult | None = None
    positions: np.ndarray | None = None  # estimated positions as read (plots without ground truth)
    map: MapQuality | None = None  # map sharpness of the scans at these poses (``dm2 eval --scans``)
    kitti: KittiOdometryError | None = None  # the KITTI odometry metric (t_err %, r_err deg/100 m)


@dataclass
class EvalReport:
    ground_truth: str | None
    relations_file: str | None
    settings: dict
    estimates: list[EstimateReport] = field(default_factory=list)
    map: dict | None = None  # how the map metrics were computed (scans, voxel, radius, ...)


def _num(v: float | None) -> float | None:
    """JSON-safe number (NaN/inf become null)."""
    return None if v is None or not math.isfinite(v) else float(v)


def rows(report: EvalReport) -> list[dict]:
    """One dict per estimate and metric, keys :data:`COLUMNS` (missing statistics are absent)."""
    out = []
    for est in report.estimates:
        if est.poses is not None:
            for key, m in est.poses.metrics.items():
                out.append({"estimate": est.label, "metric": key, "unit": m.unit, "count": m.count,
                            "value": m.stats["rmse"], **m.stats})
        if est.paper is not None:
            p = est.paper
            out.append({"estimate": est.label, "metric": "paper_ate_trans", "unit": "sqrt(m)",
                        "count": p.count, "value": p.trans})
            out.append({"estimate": est.label, "metric": "paper_ate_rot", "unit": "deg",
                        "count": p.count, "value": p.rot_deg, "mean": p.rot_deg})
        if est.relations is not None:
            s = est.relations.stats
            for key, unit in (("trans", "m"), ("trans_sq", "m^2"), ("rot", "deg"), ("rot_sq", "deg^2")):
                out.append({"estimate": est.label, "metric": f"relations_{key}", "unit": unit,
                            "count": est.relations.used, "value": s[f"{key}_mean"],
                            "mean": s[f"{key}_mean"], "std": s[f"{key}_std"]})
        if est.map is not None:
            m = est.map
            out.append({"estimate": est.label, "metric": "map_entropy", "unit": "nats", "count": m.queries,
                        "value": m.entropy, "mean": m.entropy})
            out.append({"estimate": est.label, "metric": "map_plane_variance", "unit": "m^2", "count": m.queries,
                        "value": m.plane_variance, "mean": m.plane_variance})
    return out


def to_json(report: EvalReport) -> dict:
    estimates = []
    for est in report.estimates:
        entry: dict = {"label": est.label, "path": est.path, "metrics": {}}
        if est.poses is not None:
            pe = est.poses
            entry["association"] = {"mode": pe.association, "matched": pe.n_matched, "gt_poses": pe.n_gt,
                                    "est_poses": pe.n_est, "max_diff": pe.max_diff}
            entry["alignment"] = {"mode": pe.align, "align_origin": pe.align_origin, "scale": pe.scale,
                                  "sim3": None if pe.alignment is None else pe.alignment.tolist()}
            for key, m in pe.metrics.items():
                entry["metrics"][key] = {"unit": m.unit, "count": m.count, "title": m.title,
                                         **{k: _num(v) for k, v in m.stats.items()}}
            entry["standing_still_ape_trans_rmse_m"] = _num(standing_still_rmse(
                np.asarray(pe.ref.positions_xyz), pe.align, pe.align_origin))
            entry["cautions"] = estimate_cautions(est)
        if est.paper is not None:
            entry["metrics"]["paper_ate"] = {
                "label": PAPER_LABEL, "count": est.paper.count, "trans_sqrt_m": _num(est.paper.trans),
                "rot_deg": _num(est.paper.rot_deg),
                "definition": "DeepMapping2 utils/geometry_utils.py compute_ate: rigid alignment; "
                              "trans = sqrt(mean per-frame distance), rot = mean |yaw error| (deg)",
            }
        if est.kitti is not None:
            entry["metrics"]["kitti_odometry"] = {k: _num(v) if isinstance(v, float) else v
                                                  for k, v in est.kitti.as_dict().items()}
        if est.relations is not None:
            r = est.relations
            entry["metrics"]["relations"] = {"used": r.used, "skipped": r.skipped, "planar": r.planar,
                                             "max_dt": r.max_dt, "units": {"trans": "m", "rot": "deg"},
                                             **{k: _num(v) for k, v in r.stats.items()}}
        if est.map is not None:
            entry["metrics"]["map"] = {k: _num(v) if isinstance(v, float) else v
                                       for k, v in est.map.as_dict().items()}
        estimates.append(entry)
    return {"format": FORMAT, "ground_truth": report.ground_truth, "relations": report.relations_file,
            "settings": report.settings, "map": report.map, "estimates": estimates}


def run_metrics(est: EstimateReport) -> dict[str, float]:
    """Flat metrics of one estimate for a run report's ``metrics`` (units in the names)."""
    out: dict[str, float] = {}
    if est.poses is not None:
        for key, m in est.poses.metrics.items():
            out[f"{key}_rmse_{m.unit}"] = m.stats["rmse"]
    if est.paper is not None:
        out["paper_ate_trans"] = est.paper.trans
        out["paper_ate_rot_deg"] = est.paper.rot_deg
    if est.kitti is not None:
        out.update(est.kitti.metrics())  # kitti_t_err_percent, kitti_r_err_deg_per_100m (where applicable)
    if est.relations is not None:
        out["relations_trans_mean_m"] = est.relations.stats["trans_mean"]
        out["relations_rot_mean_deg"] = est.relations.stats["rot_mean"]
    return out


def display_rows(report: EvalReport) -> tuple[list[str], list[list]]:
    header = ["estimate", "metric", "unit", "count", "value", *STAT_KEYS]
    body = [[r["estimate"], _LABELS[r["metric"]], r["unit"], r["count"], r["value"],
             *(r.get(k) for k in STAT_KEYS)] for r in rows(report)]
    return header, body


def estimate_cautions(est: EstimateReport) -> list[str]:
    """The cautions on an estimate's figures against ground truth: :func:`pose_cautions` and, where its yaw is no
    rotation error, the paper ATE rot's (:attr:`PaperATE.caution`)."""
    out = pose_cautions(est.poses) if est.poses is not None else []
    return out + ([est.paper.caution] if est.paper is not None and est.paper.caution else [])


def describe(est: EstimateReport) -> list[str]:
    """Lines on how an estimate was associated and aligned."""
    lines = []
    if est.poses is not None:
        pe = est.poses
        how = f"by time (max diff {pe.max_diff} s)" if pe.association == "time" else "by index"
        align = "origin" if pe.align_origin else pe.align
        scale = f", scale {pe.scale:.6f}" if pe.align == "sim3" else ""
        lines.append(f"{est.label}: {pe.n_matched} pose pairs associated {how} "
                     f"(gt {pe.n_gt}, estimate {pe.n_est}); alignment {align}{scale}")
        if pe.association == "index" and pe.n_gt != pe.n_est:
            lines.append(f"{est.label}: warning: associated by index (--by-index) although the lengths differ; "
                         f"only the first {pe.n_matched} poses of each are compared")
        lines += [f"{est.label}: caution: {text}" for text in pose_cautions(pe)]
    if est.relations is not None:
        r = est.relations
        lines.append(f"{est.label}: {r.used} relations used, {r.skipped} skipped (no pose within "
                     f"{r.max_dt} s); {'SE(2)' if r.planar else 'SE(3)'}")
    return lines


def map_line(report: EvalReport) -> list[str]:
    if report.map is None:
        return []
    m = report.map
    return [f"map: {m['scans']} scans voxelised at {m['voxel_m']:.4g} m ({m['points']} points), "
            f"neighbourhood radius {m['radius_m']:.4g} m (derived from the scans), {m['queries']} sampled "
            f"points; lower entropy / plane variance = sharper"]


def kitti_lines(report: EvalReport) -> list[str]:
    """Each estimate's KITTI odometry line (the figures, or why the metric does not apply)."""
    return [f"{est.label}: {est.kitti.line()}" for est in report.estimates if est.kitti is not None]


def terminal_text(report: EvalReport) -> str:
    lines = [line for est in report.estimates for line in describe(est)] + map_line(report)
    header, body = display_rows(report)
    lines += ["", format_table(header, body)]
    if kitti_lines(report):
        lines += ["", *kitti_lines(report)]
    if any(e.paper is not None for e in report.estimates):
        lines.append(f"\n{PAPER_LABEL}: the DeepMapping2 paper's definition (trans = sqrt of the mean "
                     "distance after rigid alignment, sqrt(m); rot = mean |yaw error|); not comparable "
                     "with APE")
        lines += [f"{e.label}: caution: {e.paper.caution}" for e in report.estimates
                  if e.paper is not None and e.paper.caution]
    return "\n".join(lines)
