"""Where a metric is ill-posed: the rotation APE when the alignment cannot determine the rotation, and the
"standing still" reference (the APE of a trajectory that never moves) when an estimate is within reach of it.

The rotation of an SE(3)/Sim(3) alignment is fitted to positions only. Rotating the aligned estimate by an
angle ``a`` about the reference's main axis moves its points by about ``a`` times their spread across that
axis, so the rotation whose cost equals the alignment's own residual is ``atan(rmse / spread)``. The rotation
is not determined when the reference spreads across its main axis no more than the estimate's aligned
position error (point-like at the estimate's resolution, or a noisy straight line), or when the path is
nearly collinear (:data:`LINE_RATIO` of its length). Both are ratios of the data's own scales.
"""

from __future__ import annotations

import numpy as np

from dm2_backend.evaluation.ape_rpe import PoseErrors

#: positions whose second principal spread is under this fraction of the first lie "on a line"
LINE_RATIO = 0.02
#: the standing-still reference is shown when it is within this factor of the estimate's APE trans RMSE
STILL_REACH = 2.0


def principal_spread(positions: np.ndarray) -> np.ndarray:
    """RMS spread (m) of ``positions`` (N,3) along its principal axes, largest first."""
    centred = positions - positions.mean(axis=0)
    return np.linalg.svd(centred, compute_uv=False) / np.sqrt(max(len(positions), 1))


def standing_still_rmse(ref_positions: np.ndarray, align: str, align_origin: bool) -> float:
    """APE translation RMSE (m) of a trajectory that never moves, under the same alignment: with an SE(3) /
    Sim(3) alignment it is placed at the reference's centroid, otherwise it stays at the first pose."""
    ref = np.asarray(ref_positions, dtype=np.float64)
    anchor = ref.mean(axis=0) if align in ("se3", "sim3") and not align_origin else ref[0]
    return float(np.sqrt(np.mean(np.sum((ref - anchor) ** 2, axis=1))))


def rotation_caution(ref_positions: np.ndarray, trans_rmse: float) -> str | None:
    """Why the APE rotation after an SE(3)/Sim(3) alignment means little, or None when the alignment
    determines the rotation."""
    ref = np.asarray(ref_positions, dtype=np.float64)
    if len(ref) < 3:
        return "fewer than 3 matched poses: the alignment is not determined and the APE rotation means nothing"
    spread = principal_spread(ref)
    across = float(np.hypot(spread[1], spread[2] if len(spread) > 2 else 0.0))
    hint = "(try --align-origin or --align none)"
    if spread[0] == 0 or spread[1] < LINE_RATIO * spread[0]:
        return (f"the ground-truth path is nearly a straight line ({spread[1]:.3g} m across, {spread[0]:.3g} m "
                f"along): the alignment leaves the rotation about it free and the APE rotation is not meaningful "
                f"{hint}")
    if across <= trans_rmse:
        free = np.degrees(np.arctan2(trans_rmse, across))
        return (f"the ground-truth path is nearly a point at this estimate's accuracy (RMS spread "
                f"{' x '.join(f'{s:.3g}' for s in spread)} m, aligned position error {trans_rmse:.3g} m): "
                f"a rotation of {free:.0f} deg costs the alignment no more than its residual, so the APE "
                f"rotation is not meaningful {hint}")
    return None


def pose_cautions(pe: PoseErrors) -> list[str]:
    """The cautions on an evaluation against ground truth (empty when every number means what it says)."""
    out = []
    ref = np.asarray(pe.ref.positions_xyz)
    rmse = pe.metrics["ape_trans"].stats["rmse"]
    if pe.align in ("se3", "sim3") and not pe.align_origin:
        why = rotation_caution(ref, rmse)
        if why:
            out.append(f"APE rotation: {why}")
    still = standing_still_rmse(ref, pe.align, pe.align_origin)
    if still <= STILL_REACH * rmse:
        out.append(standing_still_line(still, rmse))
    return out


def standing_still_line(still: float, rmse: float) -> str:
    """The reference line: what a trajectory that never moves would score, beside the estimate's score."""
    than = "better than" if still < rmse else "within reach of"
    return (f"standing still: a trajectory that never moves scores APE trans RMSE {still:.4g} m, {than} this "
            f"estimate's {rmse:.4g} m")
