"""The trained M-Net after a run (:mod:`dm2_backend.optim.mnet_file`) sampled on a grid and meshed by marching
cubes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.optim.mnet_file import MNet
from dm2_backend.runtime.atomic import atomic_path


def sample_grid(mnet: MNet, centers: np.ndarray) -> np.ndarray:
    """Occupancy probability at the cell centres (H, W, 2) of a 2D grid."""
    return mnet.probability(centers)


def mesh(mnet: MNet, points: np.ndarray, cell: float | None = None, max_samples: int = 1 << 22,
         near: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The M-Net's decision surface (logit 0) by marching cubes over the bounding box of the map ``points``
    (K, 3 world). The lattice step is the field's finest cell, coarsened until the box holds at most
    ``max_samples`` lattice points. The field is only trained where the scans saw, so only cubes within
    ``near`` lattice steps of a map point are meshed (and only their corners evaluated). Returns vertices
    (V, 3) in world coordinates, triangles (F, 3), vertex normals and the step."""
    from scipy.ndimage import binary_dilation
    from skimage.measure import marching_cubes

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    step = float(cell or mnet.finest_cell)
    lo, hi = points.min(0), points.max(0)
    while np.prod(np.ceil((hi - lo) / step) + 2 * near + 2) > max_samples:
        step *= 1.25
    lo = lo - (near + 1) * step
    dims = (np.ceil((hi + (near + 1) * step - lo) / step) + 1).astype(int)
    occupied = np.zeros(dims, bool)
    occupied[tuple(np.clip(np.round((points - lo) / step).astype(np.int64), 0, dims - 1).T)] = True
    mask = binary_dilation(occupied, iterations=near)
    evaluate = binary_dilation(mask, structure=np.ones((3, 3, 3), bool))  # every corner of a masked cube
    volume = np.full(dims, 10.0, np.float32)  # never a corner of a meshed cube
    where = np.argwhere(evaluate)
    volume[tuple(where.T)] = np.clip(mnet.logits(lo + where * step), -10, 10)
    if not (volume[mask].min() < 0 < volume[mask].max()):
        raise ValueError("the M-Net's occupancy does not cross 0.5 near the map")
    verts, faces, normals, _ = marching_cubes(volume, level=0.0, spacing=(step, step, step), mask=mask)
    return verts + lo, faces.astype(np.int64), normals, step


def write_ply(path: Path, verts: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None) -> None:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(verts, np.float64)),
                                  o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    if normals is not None:
        m.vertex_normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), m):
            raise OSError(f"open3d could not write {path}")
