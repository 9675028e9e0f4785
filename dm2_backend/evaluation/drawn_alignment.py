"""The alignment the evaluation pictures draw an estimate with, by the console's rule.

The pictures: a run's ``trajectory.png`` / ``errors.png`` and ``dm2 eval --plot``'s ``trajectories.png`` /
``errors_<label>.png``. They draw each estimate after the evaluation's alignment (SE(3) by default), except
where :func:`~dm2_backend.evaluation.cautions.rotation_caution` finds that an SE(3)/Sim(3) alignment is not
meaningful (a ground-truth path that is nearly a point at the estimate's accuracy, e.g. a camera turned in
place, or nearly a straight line): the rotation of that alignment is then arbitrary, and so would be the
picture. There the estimate is aligned at its first pose (evo's ``--align_origin``), the remedy the caution
names first, and the per-frame errors coloured are measured after that alignment. The numbers in the console
and the reports keep the chosen alignment (and print the caution); the figure's title says which alignment
each estimate is drawn with, and why where it is not the evaluation's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core.geometry import umeyama_alignment

from dm2_backend.evaluation.ape_rpe import PoseErrors
from dm2_backend.evaluation.cautions import rotation_caution
from dm2_backend.kernel.geometry import se3

#: how a title names each alignment
NAMES = {"se3": "SE(3)", "sim3": "Sim(3)", "origin": "at the first pose, --align-origin", "none": "none"}


@dataclass
class Drawn:
    """One estimate as a picture draws it: positions in the ground truth's frame and the per-frame errors
    after the same alignment."""

    positions: np.ndarray  # (N,3)
    trans_errors: np.ndarray  # (N,) m
    rot_errors_deg: np.ndarray  # (N,) deg
    align: str  # "se3", "sim3", "origin" or "none"
    #: the evaluation's own alignment and the caution that ruled it out for the picture (None: it is drawn)
    instead_of: str | None = None
    caution: str | None = None


def origin_aligned(ref_poses: np.ndarray, est_poses: np.ndarray) -> np.ndarray:
    """``est_poses`` (N,4,4) moved so that its first pose is the first of ``ref_poses`` (evo's ``align_origin``)."""
    return (ref_poses[0] @ se3.inverse(est_poses[0])) @ est_poses


def errors(ref_poses: np.ndarray, est_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame APE of aligned poses: translation (m) and rotation angle (deg), as evo measures them."""
    trans = np.linalg.norm(est_poses[:, :3, 3] - ref_poses[:, :3, 3], axis=1)
    rel = np.swapaxes(ref_poses[:, :3, :3], 1, 2) @ est_poses[:, :3, :3]
    return trans, np.degrees(se3.rotation_angle(rel))


def _at_origin(ref: np.ndarray, est: np.ndarray, instead_of: str, why: str) -> Drawn:
    moved = origin_aligned(ref, est)
    return Drawn(moved[:, :3, 3], *errors(ref, moved), "origin", instead_of, why)


def from_pose_errors(pe: PoseErrors) -> Drawn:
    """A ``dm2 eval`` estimate: drawn as it was evaluated (``pe.est``, evo's errors) unless the console cautions
    that its SE(3)/Sim(3) alignment is not meaningful."""
    ref = np.array(pe.ref.poses_se3)
    if pe.align in ("se3", "sim3") and not pe.align_origin:
        why = rotation_caution(ref[:, :3, 3], pe.metrics["ape_trans"].stats["rmse"])
        if why is not None:
            return _at_origin(ref, np.asarray(pe.est_raw, dtype=np.float64), pe.align, why)
    m = pe.metrics
    return Drawn(np.asarray(pe.est.positions_xyz), np.asarray(m["ape_trans"].errors),
                 np.asarray(m["ape_rot"].errors), "origin" if pe.align_origin else pe.align)


def from_poses(ref_poses: np.ndarray, est_poses: np.ndarray) -> Drawn:
    """Poses paired by index (a run's): SE(3)-aligned, as a run's metrics are, unless the console cautions that
    this alignment is not meaningful."""
    ref, est = np.asarray(ref_poses, dtype=np.float64), np.asarray(est_poses, dtype=np.float64)
    if len(ref) >= 3:
        R, t, _ = umeyama_alignment(est[:, :3, 3].T, ref[:, :3, 3].T, with_scale=False)
        aligned = se3.make_poses(R, t) @ est
        trans, rot = errors(ref, aligned)
        why = rotation_caution(ref[:, :3, 3], float(np.sqrt(np.mean(trans**2))))
        if why is None:
            return Drawn(aligned[:, :3, 3], trans, rot, "se3")
    else:
        why = rotation_caution(ref[:, :3, 3], 0.0)
    return _at_origin(ref, est, "se3", why or "")


def short_reason(caution: str) -> str:
    """The head of a caution (up to its first parenthesis or colon)."""
    return caution.split(" (")[0].split(":")[0]


def title(drawn: dict[str, Drawn]) -> str:
    """The figure title: which alignment draws each estimate and, where it is not the evaluation's, why."""
    aligns = {d.align for d in drawn.values()}
    if aligns == {"none"}:
        head = "estimates not aligned (--align none)"
    elif len(aligns) == 1:
        head = f"estimates aligned to the ground truth ({NAMES[aligns.pop()]})"
    else:
        head = "aligned to the ground truth: " + ", ".join(f"{label} ({NAMES[d.align]})" for label, d in drawn.items())
    notes = [f"{NAMES[d.instead_of]} alignment not meaningful for {label}: {short_reason(d.caution or '')}"
             for label, d in drawn.items() if d.instead_of is not None]
    return "\n".join([head, *notes])
