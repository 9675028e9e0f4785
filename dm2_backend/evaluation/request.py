"""``dm2 eval`` as a library call: the files to evaluate (:class:`EvalRequest`) in, the report and what its
outputs are drawn from (:class:`Evaluation`) out."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.evaluation import drawn_alignment, plots
from dm2_backend.evaluation.consistency_profile import consistency_profiles, flag_text, write_profiles
from dm2_backend.evaluation.evaluate import EvalOptions, evaluate
from dm2_backend.evaluation.map_quality import MapSampler, poses_of_scans
from dm2_backend.evaluation.relations import load_relations
from dm2_backend.evaluation.report import EvalReport
from dm2_backend.evaluation.report_writers import safe_name
from dm2_backend.evaluation.run_compare import read_run_report
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


def write_plots(folder: Path, evaluation: Evaluation, run_report: Path | None = None) -> tuple[list[Path], str]:
    """The trajectories, each estimate's error map and (from a refine's ``run_report``) its error against the
    epochs, as PNG files in ``folder``; returns them and a note for the console ("" when none). Each estimate is
    drawn as evaluated, or aligned at its first pose where the SE(3)/Sim(3) alignment is not meaningful
    (:mod:`~dm2_backend.evaluation.drawn_alignment`); the titles name the alignment."""
    report = evaluation.report
    gt_positions = evaluation.gt.positions if evaluation.gt is not None else None
    drawn = {est.label: drawn_alignment.from_pose_errors(est.poses) for est in report.estimates
             if est.poses is not None}
    estimates = {est.label: drawn[est.label].positions if est.label in drawn else est.positions
                 for est in report.estimates}
    written = [plots.plot_trajectories(folder / "trajectories.png", gt_positions, estimates,
                                       drawn_alignment.title(drawn) if drawn else "")]
    for label, d in drawn.items():
        errors = {"APE trans": (d.trans_errors, "m"), "APE rot": (d.rot_errors_deg, "deg")}
        written.append(plots.plot_error_map(folder / f"errors_{safe_name(label)}.png", label, d.positions, errors,
                                            gt_positions, drawn_alignment.title({label: d})))
    note = ""
    if run_report is not None:
        out = plots.plot_run_epochs(folder / "epochs.png", read_run_report(run_report))
        if out is None:
            note = f"note: {run_report}: no epoch has an 'ate' entry; no error-vs-epoch plot"
        else:
            written.append(out)
    return written, note


def write_evaluation_profiles(folder: Path, evaluation: Evaluation, planar: bool) -> tuple[list[Path], list[str]]:
    """Each estimate's consistency profile (its poses at the scans, kept with ``EvalRequest.profile``) written to
    ``folder``; returns the files and one line per estimate naming its flagged stretches."""
    scans, at_scans = evaluation.scans, evaluation.at_scans
    profiles = consistency_profiles(scans, at_scans, scans.timestamps, planar)
    lines = [f"consistency: {label}: {flag_text(prof.summary())}" for label, prof in profiles.items()]
    names = write_profiles(folder, profiles, {k: v[:, :3, 3] for k, v in at_scans.items()})
    return [folder / name for name in names], lines
