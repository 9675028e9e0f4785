"""The accuracy shown per epoch while ``dm2 refine`` trains (a light module: spawned ranks import it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from evo.core.geometry import umeyama_alignment

from dm2_backend.evaluation.relations import relations_error
from dm2_backend.kernel.trajectory import Trajectory

if TYPE_CHECKING:
    from dm2_backend.pipeline.inputs import RunInputs


def ate_rmse(gt: np.ndarray, est: np.ndarray) -> float:
    """Translation ATE RMSE (m) after rigid (SE(3)) alignment of positions."""
    R, t, _ = umeyama_alignment(est[:, :3, 3].T, gt[:, :3, 3].T, with_scale=False)
    d = est[:, :3, 3] @ R.T + t - gt[:, :3, 3]
    return float(np.sqrt((d * d).sum(1).mean()))


def relations_mean(relations: np.ndarray, timestamps: np.ndarray, poses: np.ndarray) -> float:
    return relations_error(Trajectory(poses, timestamps, planar=True), relations).stats["trans_mean"]


def gt_ate(gt: np.ndarray, frames: np.ndarray | None, poses: np.ndarray) -> float:
    """ATE of the scans that have ground truth (``frames``: their indices, None: all)."""
    return ate_rmse(gt, poses if frames is None else poses[frames])


#: the names of the per-epoch metrics: the keys of ``report.json``'s metrics they equal
ATE_METRIC = "ape_trans_rmse_m"
RELATIONS_METRIC = "relations_trans_mean_m"


@dataclass(frozen=True)
class LiveMetric:
    """A per-epoch accuracy of poses and its name (recorded with each epoch as ``ate_metric``)."""

    name: str
    fn: Callable[[np.ndarray], float]

    def __call__(self, poses: np.ndarray) -> float:
        return self.fn(poses)


def live_metric(inputs: RunInputs, timestamps: np.ndarray | None) -> LiveMetric | None:
    """Per-epoch accuracy for the progress bar: ATE against --gt, else the relations metric (picklable, for
    spawned ranks)."""
    if inputs.gt is not None:
        return LiveMetric(ATE_METRIC, partial(gt_ate, inputs.gt.poses, inputs.gt_frames))
    if inputs.relations is not None and timestamps is not None:
        return LiveMetric(RELATIONS_METRIC, partial(relations_mean, inputs.relations, timestamps))
    return None
