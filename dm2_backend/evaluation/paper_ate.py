"""The DeepMapping2 paper's ATE ("paper ATE"), as the official code computes it.

Official code: ai4ce/DeepMapping2, ``utils/geometry_utils.py``, function ``compute_ate(output, target,
rotation_representation)``, called once per epoch by
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

Where the yaw is no heading the rotation figure is kept (it is the paper's definition) and
:attr:`PaperATE.caution` says why it is not comparable: adding Euler angles composes rotations only about one
shared axis, so the figure means a heading error only where the poses' z axes are vertical (not in EuRoC's
body frame, IMU x up and z horizontal, nor in a camera frame), and it may then exceed the whole rotation error
after the same alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core.geometry import umeyama_alignment
from scipy.spatial.transform import Rotation

from dm2_backend.kernel.geometry import se3

LABEL = "paper ATE"
#: the poses' z axes count as not vertical when their median angle from the vertical line exceeds this (closer
#: to horizontal than to vertical: the last Euler angle is then no heading)
TILT_DEG = 45.0
#: the yaw error contradicts the rotation error it is a part of when its mean exceeds the mean whole rotation
#: error (after the same alignment) by this factor (for motion about z the two are equal)
PART_SLACK = 1.1


@dataclass
class PaperATE:
    """The paper's two figures and the per-frame errors behind them."""

    trans: float  # sqrt(mean distance), sqrt(m)
    rot_deg: float  # mean absolute yaw error, degrees
    trans_errors: np.ndarray  # per-frame distance after alignment, m
    rot_errors_deg: np.ndarray  # per-frame absolute yaw error, degrees
    rotation: np.ndarray  # 3x3 alignment rotation applied to the estimate
    translation: np.ndarray  # alignment translation
    #: mean whole rotation error (geodesic angle) of the estimate's orientations after the same alignment, deg
    whole_rot_deg: float = float("nan")
    #: median angle of the ground truth's / the estimate's z axes from the vertical line, deg
    tilt_deg: tuple[float, float] = (float("nan"), float("nan"))

    @property
    def count(self) -> int:
        return len(self.trans_errors)

    @property
    def caution(self) -> str | None:
        """Why the rotation figure is not comparable (with APE rot, or the paper's planar LiDAR figures), or
        None where its yaw is the heading."""
        why = []
        if self.rot_deg > PART_SLACK * self.whole_rot_deg + 1e-6:
            why.append(f"here it reads {self.rot_deg:.3g} deg, more than the whole rotation error after its "
                       f"alignment ({self.whole_rot_deg:.3g} deg mean), of which a yaw error is a part")
        tilted = [f"{t:.0f} deg ({name})" for name, t in zip(("ground truth", "estimate"), self.tilt_deg,
                                                              strict=True) if t > TILT_DEG]
        if tilted:
            why.append(f"the poses' z axes lie {' and '.join(tilted)} from the world's z (median): a body or "
                       f"camera frame with z not up, as EuRoC's IMU frame or a camera's")
        if not why:
            return None
        return (f"{LABEL} rot is not comparable with APE rot: it compares yaw angles (the last Euler XYZ angle, the "
                f"alignment's yaw added, the orientations not aligned), a rotation error only where every z axis is "
                f"the world's z; {'; '.join(why)}")


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
    whole = Rotation.from_matrix(np.swapaxes(gt_poses[:, :3, :3], 1, 2) @ R @ est_poses[:, :3, :3]).magnitude()
    return PaperATE(
        trans=float(np.sqrt(np.mean(trans_errors))),
        rot_deg=float(np.degrees(np.mean(rot))),
        trans_errors=trans_errors,
        rot_errors_deg=np.degrees(rot),
        rotation=R,
        translation=t,
        whole_rot_deg=float(np.degrees(np.mean(whole))),
        tilt_deg=(_tilt_deg(gt_poses), _tilt_deg(est_poses)),
    )


def _tilt_deg(poses: np.ndarray) -> float:
    """Median angle (deg) of the poses' z axes from the vertical line (up or down alike)."""
    z = poses[:, 2, 2] / np.maximum(np.linalg.norm(poses[:, :3, 2], axis=1), 1e-12)
    return float(np.degrees(np.median(np.arccos(np.clip(np.abs(z), 0.0, 1.0)))))
