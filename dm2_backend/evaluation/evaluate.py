"""One evaluation of an estimated trajectory, shared by ``dm2 eval`` and every run's ``report.json``.

Against ground truth: APE/RPE through evo, the paper's ATE and the KITTI odometry metric; against Freiburg
relations: the relations metric; with scans: the map's sharpness (entropy and plane variance) at the estimated poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.evaluation.ape_rpe import evaluate_poses
from dm2_backend.evaluation.kitti_odometry import kitti_odometry_error
from dm2_backend.evaluation.map_quality import MapSampler, estimate_map
from dm2_backend.evaluation.paper_ate import paper_ate
from dm2_backend.evaluation.relations import MAX_DT, relations_error
from dm2_backend.evaluation.report import EstimateReport
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory


@dataclass(frozen=True)
class EvalOptions:
    """How an estimate is compared (``dm2 eval``'s options; a run's report uses the defaults)."""

    align: str = "se3"
    align_origin: bool = False
    #: seconds between associated stamps; ``by_index``: pair the poses in order (already paired one to one,
    #: or ``dm2 eval --by-index``: the first min(N, M), whatever the stamps)
    max_diff: float = 0.01
    by_index: bool = False
    delta: float = 1.0
    delta_unit: str = "f"
    relations_max_dt: float = MAX_DT


def evaluate(est: Trajectory, label: str = "", path: str | Path = "", *, gt: Trajectory | None = None,
             relations: np.ndarray | None = None, sampler: MapSampler | None = None,
             scans: ScanSequence | None = None, gt_frames: np.ndarray | None = None,
             options: EvalOptions = EvalOptions(), kitti_frame: np.ndarray | None = None) -> EstimateReport:
    """Every metric that the given references allow for the estimate ``est``; ``gt_frames``: the poses of
    ``est`` that ``gt`` holds, in its order (None: all); ``kitti_frame``: the KITTI odometry metric evaluates
    ``kitti_frame @ T @ inv(kitti_frame)`` (KITTI's ``Tr``: LiDAR-frame poses back in the camera frame)."""
    entry = EstimateReport(label=label, path=str(path), positions=est.positions)
    if gt is not None:
        covered = est if gt_frames is None else est.subset(gt_frames)
        entry.poses = evaluate_poses(gt, covered, align=options.align, align_origin=options.align_origin,
                                     max_diff=options.max_diff, delta=options.delta, delta_unit=options.delta_unit,
                                     names=("ground truth", label or "estimate"), source=path or None,
                                     by_index=options.by_index)
        if entry.poses.n_matched >= 3:
            entry.paper = paper_ate(np.array(entry.poses.ref.poses_se3), entry.poses.est_raw)
        # on the associated poses as they are (the devkit aligns nothing)
        entry.kitti = kitti_odometry_error(np.array(entry.poses.ref.poses_se3), entry.poses.est_raw, kitti_frame)
    if relations is not None:
        entry.relations = relations_error(est, relations, max_dt=options.relations_max_dt, source=path or None)
    if sampler is not None and scans is not None:
        entry.map = estimate_map(sampler, scans, est, options.max_diff, source=path or None)
    return entry
