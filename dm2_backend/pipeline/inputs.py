"""Read what a run needs: scans, the given trajectory, and optional ground truth or relations."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.errors import InputError
from dm2_backend.evaluation.relations import load_relations
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory
from dm2_backend.geometry import se3
from dm2_backend.scans import ScanSequence, associate_scans
from dm2_backend.trajectory import Trajectory, associate_by_time

#: trajectories a scan source may carry that serve as the warm start when no --poses is given
CARRIED_WARM_START = ("odometry",)


@dataclass
class RunInputs:
    scans: ScanSequence
    given: Trajectory | None
    given_format: str | None
    given_path: Path | None
    gt: Trajectory | None = None
    relations: np.ndarray | None = None


def looks_planar(scans: ScanSequence, given: Trajectory | None, sample: int = 5) -> bool:
    """Planar when the source says so, or sampled scans and the given poses all lie in z = 0."""
    if scans.planar:
        return True
    idx = np.unique(np.linspace(0, len(scans) - 1, min(sample, len(scans))).astype(int))
    flat = all(np.abs(scans[int(i)].points[:, 2]).max() < 1e-6 for i in idx)
    return flat and (given is None or se3.is_planar(given.poses))


def load_inputs(
    scans_path: Path,
    scans_format: str | None,
    poses_path: Path | None,
    poses_format: str | None,
    options: ReadOptions,
    gt_path: Path | None = None,
    gt_format: str | None = None,
    relations_path: Path | None = None,
    max_diff: float = 0.01,
) -> RunInputs:
    scans = open_scans(scans_path, scans_format, options)
    given, fmt = None, None
    if poses_path is not None:
        given = read_trajectory(poses_path, poses_format, options)
        fmt = given.meta.get("format")
        scans, given = associate_scans(scans, given, max_diff)
    else:
        for name in CARRIED_WARM_START:
            if name in scans.trajectories:
                given, fmt = scans.trajectories[name], scans.meta.get("format")
                break
    scans.planar = looks_planar(scans, given)
    if given is not None and scans.planar:
        given.planar = True
    gt = None
    if gt_path is not None:
        gt = read_trajectory(gt_path, gt_format, options)
        gt = _gt_for_scans(gt, scans, gt_path, max_diff)
    relations = load_relations(relations_path) if relations_path is not None else None
    return RunInputs(scans, given, fmt, poses_path, gt, relations)


def _gt_for_scans(gt: Trajectory, scans: ScanSequence, path: Path, max_diff: float) -> Trajectory:
    """Ground truth with one pose per scan: by timestamp when both have them, else by index."""
    if scans.timestamps is not None and gt.timestamps is not None:
        i_scan, i_gt = associate_by_time(scans.timestamps, gt.timestamps, max_diff)
        if len(i_scan) == len(scans):
            return gt.subset(i_gt[np.argsort(i_scan)])
    if len(gt) != len(scans):
        raise InputError(path, f"ground truth has {len(gt)} poses for {len(scans)} scans")
    return gt
