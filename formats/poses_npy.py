"""dm2's ``poses.npy`` (and ``warm_start.npy``): an (N, 4, 4) array of poses, one 4x4 matrix per scan.

The run folder's exact poses (float64, no timestamps: ``poses_tum.txt`` beside it has them). Read with
``allow_pickle=False``; the bottom rows must be ``0 0 0 1`` and the rotations rotations. A trajectory whose
poses all stay in the z = 0 plane and turn about z only reads as planar (2D).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats._npy import load_numeric_npy, sniff_shape
from dm2_backend.formats.registry import ReadOptions, TrajectoryFormat, trajectory_format
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError


def read_poses_npy(path: str | Path, options: ReadOptions | None = None) -> Trajectory:
    """Poses (N,4,4) of an ``.npy`` file; :class:`InputError` naming the pose for anything else."""
    path = Path(path)
    array = load_numeric_npy(path)
    if array.ndim != 3 or array.shape[1:] != (4, 4) or len(array) == 0:
        raise InputError(path, f"shape {array.shape}, expected (N, 4, 4): one 4x4 pose per scan")
    poses = array.astype(np.float64)
    finite = np.isfinite(poses.reshape(len(poses), -1)).all(axis=1)
    if not finite.all():
        raise InputError(path, f"pose {int(np.argmax(~finite))} has NaN or infinite values")
    bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 1e-9
    if bottom.any():
        i = int(np.argmax(bottom))
        raise InputError(path, f"pose {i} has bottom row {poses[i, 3].tolist()}, expected [0, 0, 0, 1]")
    traj = Trajectory(poses=poses, planar=se3.is_planar(poses))
    return traj.validate(path)


def write_poses_npy(traj: Trajectory, path: str | Path, options: ReadOptions | None = None) -> None:
    """Write the poses (N,4,4) float64 (timestamps are not kept)."""
    with atomic_write(Path(path), "wb") as fh:
        np.save(fh, np.asarray(traj.poses, dtype=np.float64), allow_pickle=False)


def sniff(path: Path) -> bool:
    """An .npy file whose header declares a numeric (N, 4, 4) array (only the header is read)."""
    return sniff_shape(path, lambda shape: len(shape) == 3 and shape[1:] == (4, 4))


FORMAT = trajectory_format(
    TrajectoryFormat(
        name="npy",
        description="dm2 poses.npy: N x 4 x 4 array of poses (a run folder's exact poses; no timestamps)",
        read=read_poses_npy,
        write=write_poses_npy,
        suffixes=(".npy",),
        sniff=sniff,
        stamped=False,
    )
)
