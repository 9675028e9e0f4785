"""``dm2 eval`` as a library call: the files to evaluate (:class:`EvalRequest`) in, the report and what its
outputs are drawn from (:class:`Evaluation`) out."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.evaluation.evaluate import EvalOptions, evaluate
from dm2_backend.evaluation.map_quality import MapSampler, poses_of_scans
from dm2_backend.evaluation.relations import load_relations
from dm2_backend.evaluation.report import EvalReport
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError


@dataclass(frozen=True)
class Estimate:
    """One estimated trajectory: its file, its label in the outputs, how it is read."""

    path: Path
    label: str
    read: ReadOptions = field(default_factory=ReadOptions)
    format: str | None = None


@dataclass(frozen=True)
class EvalRequest:
    """What to evaluate and against what: the estimates, a ground truth (its file, format and read options),
    Freiburg relations, the scans whose map each estimate makes (``scans_read``: as ``dm2 refine`` reads them),
    how the poses are compared, and whether each estimate's poses at the scans are kept for a consistency
    profile."""

    estimates: tuple[Estimate, ...]
    options: EvalOptions = EvalOptions()
    gt_path: Path | None = None
    gt_format: str | None = None
    gt_read: ReadOptions = field(default_factory=ReadOptions)
    relations_path: Path | None = None
    scans_path: Path | None = None
    scans_format: str | None = None
    scans_read: ReadOptions = field(default_factory=ReadOptions)
    profile: bool = False


@dataclass(frozen=True)
class Evaluation:
    """The report, the ground truth and scans it was made with, and (with ``profile``) each estimate's poses
    at the scans' stamps, by label."""

    report: EvalReport
    gt: Trajectory | None
    scans: ScanSequence | None
    at_scans: dict[str, np.ndarray]


def evaluate_request(request: EvalRequest) -> Evaluation:
    """Read every file of ``request`` and evaluate each estimate against what it gives."""
    options = request.options
    gt = read_trajectory(request.gt_path, request.gt_format, request.gt_read) if request.gt_path else None
    if gt is not None and len(gt) == 0:
        raise InputError(request.gt_path, "no poses")
    relations = load_relations(request.relations_path) if request.relations_path else None
    scans = (open_scans(request.scans_path, request.scans_format, request.scans_read) if request.scans_path
             else None)
    sampler = MapSampler.from_scans(scans) if scans is not None else None
    report = EvalReport(
        ground_truth=str(request.gt_path) if request.gt_path else None,
        relations_file=str(request.relations_path) if request.relations_path else None,
        settings={"align": options.align, "align_origin": options.align_origin, "max_diff": options.max_diff,
                  "by_index": options.by_index, "delta": options.delta, "delta_unit": options.delta_unit,
                  "relations_max_dt": options.relations_max_dt},
        map=None if sampler is None else {"scans_path": str(request.scans_path), **sampler.settings_summary()},
    )
    at_scans = {}
    for estimate in request.estimates:
        est = read_trajectory(estimate.path, estimate.format, estimate.read)
        if len(est) == 0:
            raise InputError(estimate.path, "no poses")
        if request.profile and scans is not None:
            at_scans[estimate.label] = poses_of_scans(scans, est, options.max_diff, estimate.path)
        report.estimates.append(evaluate(est, estimate.label, estimate.path, gt=gt, relations=relations,
                                         sampler=sampler, scans=scans, options=options))
    return Evaluation(report, gt, scans, at_scans)
