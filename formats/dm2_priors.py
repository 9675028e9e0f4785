"""DeepMapping2's prior files: ``init_pose.npy``, ``group_matrix.npy``, ``pairwise_pose.npy``.

Semantics as in the official code (github.com/ai4ce/DeepMapping2):

* ``script/pre_processing_custom.py`` writes all three into ``<data>/<traj>/prior/``;
  ``dataset_loader/KITTI.py`` and ``script/train.py`` read them; ``utils/geometry_utils.py`` and
  ``utils/pytorch3d_utils.py`` hold the conventions.
* ``init_pose.npy``: (N, 6) float32 ``x y z a b c``, one row per scan, the scan's pose in the world
  (``transform_to_global_KITTI``: ``p_world = R @ p + t``). The angles are Euler ``"XYZ"``:
  written with ``scipy Rotation.as_euler("XYZ")`` (``mat2ang_np``) and read with pytorch3d's
  ``euler_angles_to_matrix(..., "XYZ")`` = ``Rx(a) @ Ry(b) @ Rz(c)``, i.e. scipy's intrinsic ``"XYZ"``,
  which is what :func:`dm2_backend.kernel.geometry.se3.from_xyz_euler` uses. ``train.py`` casts it to float32.
* ``group_matrix.npy``: (N, G) int; row i is ``[i, neighbour_1, ..., neighbour_{G-1}]`` (the anchor
  first; ``pre_processing_custom.py`` builds ``neighbor = [i] + ...``, the KD-tree variant
  ``script/helpful_functions/generate_group_matrix.py`` gets the anchor first as its own nearest point).
  Training uses the first ``group_size`` columns.
* ``pairwise_pose.npy``: (N, G-1, 6) float32 ``x y z`` + Euler ``"XYZ"``; entry ``[i, n-1]`` is
  ``icp_o3d(src=scan group_matrix[i, 0], dst=scan group_matrix[i, n])``, the transform taking anchor
  points into the neighbour's frame: the anchor's pose in the neighbour's frame, ``T_i^j``.
  (``compose_pose_diff`` checks ``R_anchor ~ R_j @ R_pairwise``.) It must stay float32: the model
  multiplies it with float32 tensors. (An older ``script/pairwise_icp.py`` wrote (N, G-1, 4)
  ``x y z yaw`` in the other direction; that layout is rejected.)

Our representation (:mod:`dm2_backend.kernel.prepared`): poses (N,4,4); ``groups`` (N, k) neighbour indices
without the anchor, -1 pads; ``relative`` (N, k, 4, 4) = ``T_j^i``, the neighbour in the anchor's frame,
the inverse of the file's entries. Pads are written as the anchor itself with an identity pairwise pose
(a self-pair), and a neighbour equal to its anchor reads back as a pad.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats._npy import load_numeric_npy, npy_shape, sniff_shape
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory, validate_poses
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

INIT_POSE = "init_pose.npy"
GROUP_MATRIX = "group_matrix.npy"
PAIRWISE_POSE = "pairwise_pose.npy"


def _save(path: str | Path, array: np.ndarray) -> None:
    with atomic_write(path, "wb") as fh:
        np.save(fh, array, allow_pickle=False)


def _check_finite(path: Path, array: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(array.reshape(len(array), -1)).all(axis=1)
    if bad.any():
        raise InputError(path, f"{what} {int(np.argmax(bad))} has NaN or infinite values")


def read_init_pose(path: str | Path) -> np.ndarray:
    """Poses (N,4,4) of an ``init_pose.npy`` ((N,6) ``x y z`` + Euler "XYZ")."""
    path = Path(path)
    array = load_numeric_npy(path)
    if array.ndim != 2 or array.shape[1] != 6 or len(array) == 0:
        raise InputError(path, f"shape {array.shape}, expected (N, 6): x y z + Euler XYZ angles")
    _check_finite(path, array, "row")
    poses = se3.from_xyz_euler(array.astype(np.float64)).reshape(-1, 4, 4)
    validate_poses(poses, path)
    return poses


def write_init_pose(poses: np.ndarray, path: str | Path, dtype: type = np.float64) -> None:
    """Write poses (N,4,4) as ``init_pose.npy`` (float64 by default; DeepMapping2 casts it to float32)."""
    _save(path, se3.to_xyz_euler(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)).astype(dtype))


def read_group_matrix(path: str | Path) -> np.ndarray:
    """Groups (N, G-1) int (neighbours of anchor i, -1 pads) of a ``group_matrix.npy`` (N, G)."""
    path = Path(path)
    array = load_numeric_npy(path)
    if array.ndim != 2 or array.shape[1] < 1 or len(array) == 0:
        raise InputError(path, f"shape {array.shape}, expected (N, G): anchor then neighbours per row")
    _check_finite(path, array, "row")
    fractional = (array != np.round(array)).any(axis=1)
    if fractional.any():
        raise InputError(path, f"row {int(np.argmax(fractional))} has non-integer indices")
    groups = array.astype(np.int64)
    n = len(groups)
    anchors = np.arange(n)
    if (groups[:, 0] != anchors).any():
        i = int(np.argmax(groups[:, 0] != anchors))
        raise InputError(path, f"row {i} starts with {groups[i, 0]}, expected its anchor {i}")
    out_of_range = (groups < 0) | (groups >= n)
    if out_of_range.any():
        i, c = np.argwhere(out_of_range)[0]
        raise InputError(path, f"row {i} column {c}: index {groups[i, c]} outside 0..{n - 1}")
    neighbours = groups[:, 1:].copy()
    neighbours[neighbours == anchors[:, None]] = -1
    return neighbours


def write_group_matrix(groups: np.ndarray, path: str | Path) -> None:
    """Write groups (N, k) (-1 pads) as ``group_matrix.npy`` (N, k+1) with the anchor first."""
    groups = np.asarray(groups, dtype=np.int64).reshape(len(groups), -1)
    anchors = np.arange(len(groups))
    if ((groups < -1) | (groups >= len(groups))).any():
        raise ValueError(f"group indices must be -1 (pad) or in 0..{len(groups) - 1}")
    filled = np.where(groups < 0, anchors[:, None], groups)
    _save(path, np.concatenate([anchors[:, None], filled], axis=1))


def read_pairwise_pose(path: str | Path) -> np.ndarray:
    """``relative`` (N, k, 4, 4) = T_j^i (neighbour j in anchor i's frame) of a ``pairwise_pose.npy``."""
    path = Path(path)
    array = load_numeric_npy(path)
    if array.ndim != 3 or array.shape[2] != 6 or len(array) == 0:
        old = array.ndim == 3 and array.shape[2] == 4
        hint = " (the old x y z yaw layout is not supported)" if old else ""
        raise InputError(path, f"shape {array.shape}, expected (N, G-1, 6): x y z + Euler XYZ{hint}")
    _check_finite(path, array, "row")
    anchor_in_neighbour = se3.from_xyz_euler(array.astype(np.float64).reshape(-1, 6))
    return se3.inverse(anchor_in_neighbour).reshape(array.shape[0], array.shape[1], 4, 4)


def write_pairwise_pose(relative: np.ndarray, path: str | Path, valid: np.ndarray | None = None) -> None:
    """Write ``relative`` (N, k, 4, 4) = T_j^i as ``pairwise_pose.npy`` (float32, anchor in neighbour's
    frame); entries where ``valid`` is False (pads, failed registrations) are written as identity."""
    relative = np.asarray(relative, dtype=np.float64)
    n, k = relative.shape[:2]
    flat = relative.reshape(-1, 4, 4).copy()
    if valid is not None:
        flat[~np.asarray(valid, bool).reshape(-1)] = np.eye(4)
    _save(path, se3.to_xyz_euler(se3.inverse(flat)).reshape(n, k, 6).astype(np.float32))


def read_priors(folder: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(poses, groups, relative)`` of a DeepMapping2 ``prior/`` folder, checked for agreeing sizes."""
    folder = Path(folder)
    poses = read_init_pose(folder / INIT_POSE)
    groups = read_group_matrix(folder / GROUP_MATRIX)
    relative = read_pairwise_pose(folder / PAIRWISE_POSE)
    if not len(poses) == len(groups) == len(relative):
        sizes = f"{len(poses)} poses, {len(groups)} groups and {len(relative)} pairwise rows"
        raise InputError(folder, sizes + " (must be equal)")
    if relative.shape[1] > groups.shape[1]:
        counts = f"{relative.shape[1]} pairwise poses per row for {groups.shape[1]} neighbours"
        raise InputError(folder, counts)
    return poses, groups, relative


def write_priors(
    folder: str | Path, poses: np.ndarray, groups: np.ndarray, relative: np.ndarray,
    valid: np.ndarray | None = None,
) -> None:
    """Write the three prior files into ``folder``; pads (-1) count as invalid pairs."""
    folder = Path(folder)
    groups = np.asarray(groups)
    mask = groups >= 0 if valid is None else np.asarray(valid, bool) & (groups >= 0)
    write_init_pose(poses, folder / INIT_POSE)
    write_group_matrix(groups, folder / GROUP_MATRIX)
    write_pairwise_pose(relative, folder / PAIRWISE_POSE, mask)


def _read(path: Path, options: ReadOptions) -> Trajectory:
    return Trajectory(poses=read_init_pose(path))


def _write(traj: Trajectory, path: Path, options: ReadOptions) -> None:
    write_init_pose(traj.poses, path)


def sniff(path: Path) -> bool:
    """An .npy file whose header declares a numeric (N, 6) array (only the header is read)."""
    return sniff_shape(path, lambda shape: len(shape) == 2 and shape[1] == 6)


def describe(path: Path) -> list[tuple[str, str]]:
    rows = []
    for name in (GROUP_MATRIX, PAIRWISE_POSE):
        other = path.with_name(name)
        if other.is_file():
            try:
                shape = " x ".join(str(s) for s in npy_shape(other)[0])
            except (InputError, OSError):
                shape = "unreadable"
            rows.append((name, shape))
    return rows


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="dm2",
        description="DeepMapping2 init_pose.npy: N x 6, x y z + Euler XYZ angles",
        read=_read,
        write=_write,
        suffixes=(".npy", "init_pose.npy"),
        sniff=sniff,
        describe=describe,
        stamped=False,
    )
)
