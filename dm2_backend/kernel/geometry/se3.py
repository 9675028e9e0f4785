"""The one SE(3)/SO(3) toolkit of dm2 (numpy + scipy Rotation).

Poses are 4x4 float64 homogeneous matrices, stacked as (N, 4, 4). Quaternion orders are always named
explicitly: ``"xyzw"`` (scipy, TUM, ROS) or ``"wxyz"`` (EuRoC, g2o is xyzw).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

QuatOrder = Literal["xyzw", "wxyz"]

#: Default tolerance for "is this a rotation" checks on parsed input (orthonormality and det).
ROTATION_TOL = 1e-3


def _rotation(R: np.ndarray) -> Rotation:
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64))


def make_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotations (N,3,3) and translations (N,3) into poses (N,4,4); also accepts single ones."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    single = R.ndim == 2
    R, t = R.reshape(-1, 3, 3), t.reshape(-1, 3)
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    return T[0] if single else T


def identity(n: int | None = None) -> np.ndarray:
    """The identity pose, or ``n`` stacked identities."""
    return np.eye(4) if n is None else np.tile(np.eye(4), (n, 1, 1))


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of one pose (4,4) or many (N,4,4), exploiting the rigid structure."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ri = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Ri
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Ri, t)
    out[..., 3, 3] = 1.0
    return out


def relative(Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """Pose of ``b`` expressed in the frame of ``a``: ``inv(Ta) @ Tb``."""
    return inverse(Ta) @ np.asarray(Tb, dtype=np.float64)


def interpolate(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses (M,4,4) at ``query`` times from poses (N,4,4) at increasing ``times``: rotation by slerp,
    translation linearly; a query outside ``[times[0], times[-1]]`` takes the nearest end's pose."""
    times = np.asarray(times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    q = np.clip(np.asarray(query, dtype=np.float64), times[0], times[-1])
    out = identity(len(q))
    if len(times) == 1:
        out[:] = poses[0]
        return out
    out[:, :3, :3] = Slerp(times, _rotation(poses[:, :3, :3]))(q).as_matrix()
    out[:, :3, 3] = np.stack([np.interp(q, times, poses[:, k, 3]) for k in range(3)], axis=1)
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one pose to points (M,3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def quat_to_matrix(q: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Quaternions (N,4) or (4,) in the named order to rotation matrices; normalises the input."""
    q = np.asarray(q, dtype=np.float64)
    if order == "wxyz":
        q = np.roll(q, -1, axis=-1)
    elif order != "xyzw":
        raise ValueError(f"unknown quaternion order {order!r}")
    return Rotation.from_quat(q).as_matrix()


def matrix_to_quat(R: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Rotation matrices to unit quaternions in the named order, with a non-negative scalar part."""
    q = _rotation(R).as_quat(canonical=True)
    return np.roll(q, 1, axis=-1) if order == "wxyz" else q


def from_xyz_quat(xyz: np.ndarray, q: np.ndarray, order: QuatOrder) -> np.ndarray:
    """Poses from positions and quaternions."""
    return make_poses(quat_to_matrix(q, order), xyz)


def to_xyz_quat(T: np.ndarray, order: QuatOrder) -> tuple[np.ndarray, np.ndarray]:
    """Positions and quaternions of poses."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3], order)


def euler_xyz_to_matrix(angles: np.ndarray) -> np.ndarray:
    """Euler "XYZ" angles (scipy's intrinsic ``"XYZ"``): ``R = Rx(a) @ Ry(b) @ Rz(c)``."""
    return Rotation.from_euler("XYZ", np.asarray(angles, dtype=np.float64)).as_matrix()


def matrix_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_xyz_to_matrix`."""
    return _rotation(R).as_euler("XYZ")


def from_xyz_euler(v: np.ndarray) -> np.ndarray:
    """Poses from (N,6) ``x y z a b c`` with Euler "XYZ" angles (DeepMapping2 ``init_pose.npy``)."""
    v = np.asarray(v, dtype=np.float64)
    return make_poses(euler_xyz_to_matrix(v[..., 3:]), v[..., :3])


def to_xyz_euler(T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`from_xyz_euler`."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], matrix_to_euler_xyz(T[..., :3, :3])], axis=-1)


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (fixed axes x, y, z): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    return Rotation.from_euler("xyz", np.asarray(rpy, dtype=np.float64)).as_matrix()


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix`: ``roll pitch yaw`` of rotation matrices."""
    return _rotation(R).as_euler("xyz")


def from_xy_yaw(v: np.ndarray) -> np.ndarray:
    """Planar poses from (N,3) ``x y yaw`` (z = 0)."""
    v = np.asarray(v, dtype=np.float64)
    R = Rotation.from_euler("z", v[..., 2:3]).as_matrix()
    t = np.concatenate([v[..., :2], np.zeros_like(v[..., :1])], axis=-1)
    return make_poses(R, t)


def to_xy_yaw(T: np.ndarray) -> np.ndarray:
    """``x y yaw`` of (planar) poses; yaw in (-pi, pi]."""
    T = np.asarray(T, dtype=np.float64)
    yaw = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    return np.stack([T[..., 0, 3], T[..., 1, 3], yaw], axis=-1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def rotation_error(R: np.ndarray) -> np.ndarray:
    """Per-matrix deviation from SO(3): max of ``|R^T R - I|`` and ``|det R - 1|`` (inf where huge entries
    overflow it, without numpy's warnings: such a matrix is no rotation)."""
    R = np.asarray(R, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        orth = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
        err = np.maximum(orth, np.abs(np.linalg.det(R) - 1.0))
    return np.where(np.isnan(err), np.inf, err)


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (SVD), to remove print rounding from parsed matrices."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.ones(U.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (axis * angle) of rotation matrices."""
    return _rotation(R).as_rotvec()


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors."""
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotation matrices."""
    return np.linalg.norm(log_so3(R), axis=-1)


def is_planar(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True when all poses lie in the z = 0 plane and rotate about z only."""
    T = np.asarray(T, dtype=np.float64)
    return bool(
        np.all(np.abs(T[..., 2, 3]) < tol)
        and np.all(np.abs(T[..., 2, :2]) < tol)
        and np.all(np.abs(T[..., :2, 2]) < tol)
    )
