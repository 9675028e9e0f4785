"""Whether the optimiser starts from locally accurate poses: it then takes small pose steps without drift
terms; a drifting start gets full steps and drift terms (see ``OptimConfig.drift`` / ``lr_pose``)."""

from __future__ import annotations

import numpy as np

from dm2_backend.kernel.geometry import se3


def disagreement(poses: np.ndarray, groups: np.ndarray, relative: np.ndarray, valid: np.ndarray,
                 lever: float) -> float | None:
    """Median over the valid pairs of how far the poses' relative pose is from the pairwise registration:
    translation plus rotation angle times ``lever`` (m); None without valid pairs."""
    rows, cols = np.nonzero(valid & (groups >= 0))
    if len(rows) == 0:
        return None
    E = se3.relative(relative[rows, cols], se3.relative(poses[rows], poses[groups[rows, cols]]))
    return float(np.median(np.linalg.norm(E[:, :3, 3], axis=1) + se3.rotation_angle(E[:, :3, :3]) * lever))


def locally_accurate(spread: float | None, unit: float, below: float) -> bool:
    """A start is locally accurate when its disagreement is under ``below`` units (no pairs: not known to be)."""
    return spread is not None and spread < below * unit
