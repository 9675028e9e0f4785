"""Map quality without ground truth: mean map entropy (MME) and mean plane variance (MPV).

For a map point p with the map points within radius r of it, Σ their covariance:

* entropy  h(p) = ½ ln det(2πe Σ)   (the differential entropy of a Gaussian; lower = sharper map)
* plane variance  v(p) = λ_min(Σ)   (variance along the local surface normal, m²)

MME and MPV are the means over sampled map points whose neighbourhood holds at least ``min_points`` points
(Razlaw et al., "Evaluation of registration methods for sparse 3D laser scans", ECMR 2015). Planar (2D laser)
maps use 2x2 covariances of x, y.

Each scan is voxelised once in its sensor frame (:class:`MapSampler`); every set of poses then places the same
points, so the same points are sampled for every estimate and the numbers of two estimates compare.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from dm2_backend.kernel.geometry.voxels import group_rows
from dm2_backend.kernel.scan_scale import point_spacing
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.kernel.trajectory import Trajectory, associate_by_time, interpolate_gaps
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.progress import progress as progress_of
from dm2_backend.runtime.threads import ordered_map

log = logging.getLogger(__name__)

DEFINITION = ("mean over sampled map points of 1/2 ln det(2 pi e Sigma) (map_entropy, nats) and of the "
              "smallest eigenvalue of Sigma (map_plane_variance_m2), Sigma the covariance of the map points "
              "within radius_m; lower is sharper")

#: voxel of the metric's map = the larger of the scans' point spacing and median range / VOXEL_DIVISOR;
#: radius = RADIUS_VOXELS voxels (enough points on a surface for a covariance, small enough to stay planar)
VOXEL_DIVISOR = 200.0
RADIUS_VOXELS = 3.0


@dataclass
class MapQuality:
    """The map metrics of one set of poses."""

    entropy: float  # MME, nats (lower = sharper)
    plane_variance: float  # MPV, m^2
    radius: float  # m
    queries: int  # sampled map points with enough neighbours
    points: int  # map points

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class MapSettings:
    """How the map is built and probed; every length None is derived from the scans (see :func:`derive`)."""

    voxel: float | None = None
    radius: float | None = None
    queries: int = 5_000
    #: at most this many map points in all (each scan's voxelised points are thinned evenly to fit)
    max_points: int = 500_000
    min_points: int | None = None  # default: 10 in 3D, 5 in 2D
    seed: int = 0


class MapSampler:
    """The scans voxelised once, ready to be placed by any poses."""

    def __init__(self, clouds: list[np.ndarray], planar: bool, voxel: float, radius: float,
                 settings: MapSettings) -> None:
        self.planar = planar
        self.voxel, self.radius = voxel, radius
        self.settings = settings
        self.clouds = clouds
        self.offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])])
        total = int(self.offsets[-1])
        rng = np.random.default_rng(settings.seed)
        self.query_index = np.sort(rng.choice(total, min(settings.queries, total), replace=False))
        self.min_points = settings.min_points or (5 if planar else 10)
        self._memo: dict[bytes, MapQuality] = {}

    @classmethod
    def from_scans(cls, scans: ScanSequence, settings: MapSettings | None = None, progress: bool = False
                   ) -> MapSampler:
        settings = settings or MapSettings()
        voxel, radius = derive(scans, settings)
        budget = max(1, settings.max_points // max(len(scans), 1))
        bar = progress_of(scans, "map scans", total=len(scans), unit="scan", enabled=progress)
        clouds = list(ordered_map(lambda scan: _thin(voxelise(scan.points, voxel), budget), bar))
        return cls(clouds, scans.planar, voxel, radius, settings)

    def world(self, poses: np.ndarray) -> np.ndarray:
        """All map points placed by ``poses`` (N,4,4): (P,3) float64."""
        parts = [c @ T[:3, :3].T + T[:3, 3] for c, T in zip(self.clouds, np.asarray(poses), strict=True)]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def settings_summary(self) -> dict:
        return {"scans": len(self.clouds), "voxel_m": self.voxel, "radius_m": self.radius,
                "points": int(self.offsets[-1]), "queries": len(self.query_index), "min_points": self.min_points,
                "definition": DEFINITION}

    def entropy(self, poses: np.ndarray) -> float:
        return self.evaluate(poses).entropy

    def evaluate(self, poses: np.ndarray) -> MapQuality:
        """MME and MPV of the map that ``poses`` make (remembered: a run scores its start and result twice)."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        key = hashlib.sha1(poses.tobytes()).digest()
        if key not in self._memo:
            pts = self.world(poses)
            self._memo[key] = map_quality(pts[:, :2] if self.planar else pts, self.query_index, self.radius,
                                          self.min_points)
        return self._memo[key]


def voxelise(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel: the mean of its points (float64), in the order of the voxel indices."""
    pts = np.asarray(points, dtype=np.float64)
    if voxel <= 0 or len(pts) == 0:
        return pts
    inverse, n = group_rows(np.floor(pts / voxel).astype(np.int64))
    counts = np.bincount(inverse, minlength=n)
    sums = np.stack([np.bincount(inverse, weights=pts[:, d], minlength=n) for d in range(3)], 1)
    return sums / counts[:, None]


def _thin(points: np.ndarray, budget: int) -> np.ndarray:
    if len(points) <= budget:
        return points
    return points[np.linspace(0, len(points) - 1, budget).astype(int)]


def derive(scans: ScanSequence, settings: MapSettings, sample: int = 10) -> tuple[float, float]:
    """Voxel = median range / 200, at least the scans' own point spacing; radius = 3 voxels."""
    if settings.voxel is not None and settings.radius is not None:
        return settings.voxel, settings.radius
    idx = np.unique(np.linspace(0, len(scans) - 1, min(sample, len(scans))).astype(int))
    pts = [scans[int(i)].points for i in idx]
    ranges = np.concatenate([np.linalg.norm(p, axis=1) for p in pts])
    spacing = float(np.median([_spacing(p) for p in pts]))
    voxel = settings.voxel or max(float(np.median(ranges)) / VOXEL_DIVISOR, spacing, 1e-3)
    return voxel, settings.radius or RADIUS_VOXELS * voxel


def _spacing(points: np.ndarray, cap: int = 50_000) -> float:
    """Median nearest-neighbour distance within a scan (evenly thinned to ``cap`` points: an upper bound)."""
    return point_spacing(np.asarray(points)[:: max(1, len(points) // cap)]) if len(points) >= 2 else 0.0


def map_quality(points: np.ndarray, query_index: np.ndarray, radius: float, min_points: int) -> MapQuality:
    """MME and MPV of ``points`` (P,D) probed at ``points[query_index]`` with neighbourhoods of ``radius``."""
    if len(points) == 0 or len(query_index) == 0:
        return MapQuality(float("nan"), float("nan"), radius, 0, len(points))
    tree = cKDTree(points)
    entropy, plane = [], []
    for chunk in np.array_split(query_index, max(1, len(query_index) // 1000)):  # bounded neighbour lists
        h, v = _neighbourhoods(points, tree, chunk, radius, min_points)
        entropy.append(h)
        plane.append(v)
    entropy, plane = np.concatenate(entropy), np.concatenate(plane)
    if len(entropy) == 0:
        return MapQuality(float("nan"), float("nan"), radius, 0, len(points))
    return MapQuality(float(entropy.mean()), float(plane.mean()), radius, len(entropy), len(points))


def _neighbourhoods(points: np.ndarray, tree: cKDTree, query_index: np.ndarray, radius: float,
                    min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Entropy and smallest eigenvalue of the neighbourhoods of ``points[query_index]`` with enough points."""
    neighbours = tree.query_ball_point(points[query_index], radius)
    counts = np.fromiter((len(n) for n in neighbours), int, len(neighbours))
    keep = counts >= min_points
    if not keep.any():
        return np.zeros(0), np.zeros(0)
    flat = np.concatenate([np.asarray(n, dtype=np.int64) for n, k in zip(neighbours, keep, strict=True) if k])
    counts = counts[keep]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # centred on the query point first (numerically safe), then the usual covariance of the neighbourhood
    x = points[flat] - np.repeat(points[query_index[keep]], counts, axis=0)
    mean = np.add.reduceat(x, starts, axis=0) / counts[:, None]
    outer = np.add.reduceat(x[:, :, None] * x[:, None, :], starts, axis=0) / counts[:, None, None]
    cov = outer - mean[:, :, None] * mean[:, None, :]
    # an exactly flat neighbourhood (simulated walls) has a zero eigenvalue: floor it at (radius / 1000)^2
    eig = np.clip(np.linalg.eigvalsh(cov), (1e-3 * radius) ** 2, None)
    return 0.5 * np.log(2 * np.pi * np.e * eig).sum(axis=1), eig[:, 0]  # ½ ln det(2πe Σ), λ_min


def estimate_map(sampler: MapSampler, scans: ScanSequence, est: Trajectory, max_diff: float = 0.01,
                 source=None) -> MapQuality:
    """Map metrics of the scans placed by an estimated trajectory (:func:`poses_of_scans`)."""
    return sampler.evaluate(poses_of_scans(scans, est, max_diff, source))


def poses_of_scans(scans: ScanSequence, est: Trajectory, max_diff: float = 0.01, source=None) -> np.ndarray:
    """One pose of ``est`` per scan, associated by time (else by index); every scan needs its pose, so that
    every estimate is scored on the same map points; from an estimate denser than the scans, a scan in a short
    gap of it takes the pose interpolated at its stamp (``trajectory.interpolate_gaps``, logged)."""
    if scans.timestamps is not None and est.timestamps is not None:
        i_scan, i_pose = associate_by_time(scans.timestamps, est.timestamps, max_diff)
        if len(i_scan) == len(scans):
            return est.poses[i_pose[np.argsort(i_scan)]]
        filled = interpolate_gaps(scans.timestamps, est, i_scan, i_pose)
        if filled is not None:
            log.info("%s: %s", source or "estimate", filled.describe())
            return filled.trajectory.poses
        if len(est) != len(scans):
            raise InputError(source, f"only {len(i_scan)} of {len(scans)} scans have a pose within {max_diff} s "
                                      "(see --max-diff)")
    elif len(est) != len(scans):
        raise InputError(source, f"{len(est)} poses for {len(scans)} scans and no timestamps to associate by")
    return est.poses  # by index
