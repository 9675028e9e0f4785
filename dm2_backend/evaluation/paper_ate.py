"""The DeepMapping2 paper's ATE ("paper ATE"), as the official code computes it.

Official code: ai4ce/DeepMapping2, ``utils/geometry_utils.py``, function ``compute_ate(output, target,
rotation_representation)`` (commit bc13e4a9826a3c8a5180c4b957b97d80e9a6a4a7), called once per epoch by
``script/train_KITTI_amp.py`` with the estimated and ground-truth poses of every frame. It:

1. rigidly aligns the estimated positions onto the ground-truth ones (Kabsch/Umeyama without scale,
   ``rigid_transform_kD``);
2. translation: per-frame error ``e_i = ||R p_i + t - g_i||`` and reports ``sqrt(mean(e_i))`` -- the
   square root of the MEAN DISTANCE, not an RMSE; its unit is sqrt(m). It is smaller than the RMSE when
   errors exceed 1 m and larger below. Compare it only with other "paper ATE" figures;
3. rotation: yaw only -- the last Euler "XYZ" angle of each estimated rotation plus that of the alignment
   rotation, against the last Euler "XYZ" angle of the ground truth, both wrapped to [-pi, pi]; the error
   is ``|dyaw|`` folded to [0, pi] and it reports the mean, in degrees. Meaningful for planar motion about z
   (LiDAR frame); with camera-frame poses (KITTI's y-down) that angle is not the heading.

The same associated pose pairs as APE/RPE are used. The alignment is this metric's own, independent of
``--align``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core.geometry import umeyama_alignment

from dm2_backend.geometry import se3

LABEL = "paper ATE"


@dataclass
class PaperATE:
    """The paper's two figures and the per-frame errors behind them."""

    trans: float  # sqrt(mean distance), sqrt(m)
    rot_deg: float  # mean absolute yaw error, degrees
    trans_errors: np.ndarray  # per-frame distance after alignment, m
    rot_errors_deg: np.ndarray  # per-frame absolute yaw error, degrees
    rotation: np.ndarray  # 3x3 alignment rotation applied to the estimate
    translation: np.ndarray  # alignment translation

    @property
    def count(self) -> int:
        return len(self.trans_errors)


def paper_ate(gt_poses: np.ndarray, est_poses: np.ndarray) -> PaperATE:
    """Paper ATE of associated poses (N,4,4) (estimate ``est_poses`` against ground truth ``gt_poses``)."""
    gt_poses = np.asarray(gt_poses, dtype=np.float64)
    est_poses = np.asarray(est_poses, dtype=np.float64)
    if gt_poses.shape != est_poses.shape or len(gt_poses) < 3:
        raise ValueError(f"need >= 3 pose pairs of equal count, got {len(gt_poses)}/{len(est_poses)}")
    p_est, p_gt = est_poses[:, :3, 3], gt_poses[:, :3, 3]
    R, t, _ = umeyama_alignment(p_est.T, p_gt.T, with_scale=False)
    aligned = p_est @ R.T + t
    trans_errors = np.linalg.norm(aligned - p_gt, axis=1)

    yaw_align = se3.matrix_to_euler_xyz(R)[2]
    yaw_est = se3.wrap_angle(se3.matrix_to_euler_xyz(est_poses[:, :3, :3])[:, 2] + yaw_align)
    yaw_gt = se3.wrap_angle(se3.matrix_to_euler_xyz(gt_poses[:, :3, :3])[:, 2])
    rot = np.abs(yaw_est - yaw_gt)
    rot = np.where(rot > np.pi, 2 * np.pi - rot, rot)
    return PaperATE(
        trans=float(np.sqrt(np.mean(trans_errors))),
        rot_deg=float(np.degrees(np.mean(rot))),
        trans_errors=trans_errors,
        rot_errors_deg=np.degrees(rot),
        rotation=R,
        translation=t,
    )
