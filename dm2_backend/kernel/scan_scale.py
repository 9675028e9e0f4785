"""Lengths taken from the data: point spacing within a scan, the scans' range (what every length default of dm2
is derived from)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from dm2_backend.kernel.prepared import ScanScale
from dm2_backend.kernel.scans import ScanSequence


def point_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance within one scan (open3d KD-tree)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    d = np.asarray(pcd.compute_nearest_neighbor_distance())
    return float(np.median(d[d > 0])) if (d > 0).any() else 0.0


def derive_scale(seq: ScanSequence, sample: int = 20) -> ScanScale:
    """Lengths taken from the data: median/90th-percentile range and median point spacing of raw scans."""
    idx = np.unique(np.linspace(0, len(seq) - 1, min(sample, len(seq))).astype(int))
    ranges, spacings = [], []
    for i in idx:
        pts = seq[int(i)].points
        r = np.linalg.norm(pts, axis=1)
        ranges.append(r)
        spacings.append(point_spacing(pts[:: max(1, len(pts) // 4096)]))
    r = np.concatenate(ranges)
    return ScanScale(range_median=float(np.median(r)), range_p90=float(np.percentile(r, 90)),
                     spacing_raw=float(np.median(spacings)))
