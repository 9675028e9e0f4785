"""OctoMap (``.bt``, the binary maximum-likelihood tree ``octovis`` and ``octomap_server`` load) from the scans
at their final poses, with ``pyoctomap`` (the optional ``maps`` extra): each scan is inserted as a point cloud
from its sensor position, so OctoMap ray-casts free space along every beam (its default sensor model, hit 0.7,
miss 0.4, clamping 0.12 / 0.97)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dm2_backend.runtime.atomic import atomic_path
from dm2_backend.runtime.memory import release_freed_memory

INSTALL_HINT = "pip install 'dm2[maps]' (or: pip install pyoctomap)"


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message says how to install it."""


def require_pyoctomap():
    try:
        import pyoctomap
    except ImportError as exc:
        raise MissingExtra(f"OctoMap export needs pyoctomap: {INSTALL_HINT}") from exc
    return pyoctomap


def write_octomap(path: Path, scans: Iterable[tuple[np.ndarray, np.ndarray]], resolution: float,
                  max_range: float = -1.0) -> dict:
    """Insert ``scans`` (sensor position (3,), world points (M, 3)) into an OcTree of ``resolution`` (m) and
    write it as ``.bt``. Returns a summary (resolution, scans, points, leaf nodes)."""
    pyoctomap = require_pyoctomap()
    tree = pyoctomap.OcTree(float(resolution))
    n_scans = n_points = 0
    for sensor, points in scans:
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if len(pts) == 0:
            continue
        tree.insertPointCloud(pts, np.ascontiguousarray(np.asarray(sensor, dtype=np.float64).reshape(3)),
                              float(max_range), True, True)  # lazy_eval, discretize (one update per voxel)
        n_scans += 1
        n_points += len(pts)
    tree.updateInnerOccupancy()
    with atomic_path(path) as tmp:
        if not tree.writeBinary(str(tmp)):
            raise OSError(f"pyoctomap could not write {path}")
    summary = {"resolution": float(resolution), "scans": n_scans, "points": n_points,
               "leaf_nodes": int(tree.getNumLeafNodes())}
    del tree
    release_freed_memory()
    return summary


def read_octomap(path: Path):
    """The OcTree of a ``.bt`` file (pyoctomap)."""
    pyoctomap = require_pyoctomap()
    tree = pyoctomap.OcTree(0.1)
    if not tree.readBinary(str(path)):
        raise OSError(f"pyoctomap could not read {path}")
    return tree


def occupancy_at(tree, points: np.ndarray) -> np.ndarray:
    """Per point: 1 occupied, 0 free, -1 unknown (no node)."""
    out = np.full(len(points), -1, np.int8)
    for k, p in enumerate(np.asarray(points, dtype=np.float64)):
        node = tree.search([float(p[0]), float(p[1]), float(p[2])])
        if node is not None:
            out[k] = 1 if tree.isNodeOccupied(node) else 0
    return out
