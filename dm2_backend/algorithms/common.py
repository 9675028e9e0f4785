"""Shared helpers of the preparation plugins: length scales from :class:`Frames`, planar pose helpers,
point clouds built once (open3d with normals for 3D; KD-tree and 2D normals for planar laser scans) and
topology assembly. ICP is in :mod:`.icp`, alignment checks in :mod:`.gates`."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames, ScanScale, Topology
from dm2_backend.kernel.scan_scale import point_spacing
from dm2_backend.runtime.errors import InputError

#: ICP variants; "auto" is GICP for 3D clouds (sparse down-sampled scans suit its covariances better than
#: point-to-plane's normals) and 2D point-to-line for planar scans
METHODS = ("auto", "point-to-plane", "point-to-point", "gicp")


def lengths(frames: Frames) -> ScanScale:
    """``frames.scale`` completed from the points where lengths are not measured (frames built by hand); the
    voxel 0 (none) there. ``spacing_raw`` stays as it is."""
    s = frames.scale
    if not frames.points:
        raise InputError(None, "no frames to prepare")
    sub = frames.points[:: max(1, len(frames) // 20)]
    if s.range_median is None or s.range_p90 is None:
        r = np.concatenate([np.linalg.norm(p, axis=1) for p in sub])
        s = replace(s, range_median=float(np.median(r)) if s.range_median is None else s.range_median,
                    range_p90=float(np.percentile(r, 90)) if s.range_p90 is None else s.range_p90)
    if s.spacing is None:
        s = replace(s, spacing=float(np.median([point_spacing(p) for p in sub if len(p) > 1])))
    if s.voxel is None:
        s = replace(s, voxel=0.0)
    return s


def fine_distance(scale: ScanScale) -> float:
    """Correspondence distance for a converged alignment: three point spacings (or voxels)."""
    return 3.0 * max(scale.voxel, scale.spacing)


def resolve_method(method: str, planar: bool) -> str:
    """The concrete ICP method for ``method`` (checked) on planar or 3D data."""
    if method not in METHODS:
        raise InputError(None, f"unknown ICP method {method!r}; choices: {', '.join(METHODS)}")
    if method == "auto":
        return "point-to-plane" if planar else "gicp"
    return method


def project_planar(T: np.ndarray) -> np.ndarray:
    """Keep x, y and yaw of a pose (or poses): the nearest planar pose."""
    x, y, yaw = np.moveaxis(se3.to_xy_yaw(T), -1, 0)
    return planar_pose(x, y, yaw)


def orthonormal(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected onto SO(3): chaining thousands of ICP results (and velocities
    computed from them) otherwise lets rounding grow until the poses are no longer rigid."""
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = se3.project_to_so3(out[:3, :3])
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (radians) from the trace; cheap for single matrices in loops."""
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


def planar_pose(x, y, yaw) -> np.ndarray:
    """Pose(s) (4,4) from x, y, yaw (cheap: called per ICP step)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros(np.shape(yaw) + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 3] = c, -s, x
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 3] = s, c, y
    T[..., 2, 2] = T[..., 3, 3] = 1.0
    return T


@dataclass
class Match:
    """ICP result: ``T`` maps source points into the target frame."""

    T: np.ndarray
    fitness: float  # fraction of source points with a correspondence within the final distance
    rmse: float  # rms distance of those correspondences
    #: the registration's Gauss-Newton information J^T J over those correspondences in point-to-plane form
    #: (:func:`dm2_backend.algorithms.icp.point_to_plane_hessian`; planar: point-to-line, (3, 3) on [x y yaw]),
    #: for unit residual variance, and the rms of those point-to-plane residuals (m; the noise of the matched
    #: surfaces, where ``rmse`` is mostly the point spacing); None when the registration does not give them
    hessian: np.ndarray | None = None
    plane_rmse: float | None = None


class Cloud:
    """One frame's (or local map's) points, with what registration needs built once, on first use
    (:meth:`ensure` builds it ahead, e.g. before clouds are shared between threads)."""

    def __init__(self, points: np.ndarray, planar: bool, normal_radius: float) -> None:
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.planar = planar
        self.normal_radius = normal_radius
        self._tree: cKDTree | None = None
        self._normals: np.ndarray | None = None
        self._covariances = False
        #: what other modules derive from the points and keep with the cloud (e.g. the free-space gate's depth
        #: image), keyed by what it is
        self.derived: dict = {}
        if planar:
            self.xy = np.ascontiguousarray(self.points[:, :2])
            self.pcd = None
        else:
            self.pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))

    def __len__(self) -> int:
        return len(self.points)

    def ensure(self, method: str, role: str = "both") -> Cloud:
        """Build what ``method`` needs of this cloud as ``"source"``, ``"target"`` or ``"both"``."""
        if method == "gicp" and not self.planar and not self._covariances:
            self.pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(20))
            self._covariances = True
        # planar clouds: every method but point-to-point runs the 2D point-to-line ICP
        if role != "source" and (method == "point-to-plane" or (self.planar and method != "point-to-point")):
            self.normals  # noqa: B018  (builds them)
        if role == "both":
            self.tree  # noqa: B018
        return self

    @property
    def tree(self) -> cKDTree:
        """scipy KD-tree of the points (x, y only when planar), built on first use."""
        if self._tree is None:
            self._tree = cKDTree(self.xy if self.planar else self.points)
        return self._tree

    @property
    def normals(self) -> np.ndarray:
        """Unit normals: 2D from the neighbours of planar points, else open3d's (built on first use)."""
        if self._normals is None:
            if self.planar:
                self._normals = normals_2d(self.xy, self.tree)
            else:
                param = o3d.geometry.KDTreeSearchParamHybrid(radius=self.normal_radius, max_nn=20)
                self.pcd.estimate_normals(param)
                self._normals = np.asarray(self.pcd.normals)
        return self._normals


def voxel_cloud(points: np.ndarray, voxel: float, planar: bool, normal_radius: float) -> Cloud:
    """A :class:`Cloud` of ``points`` (e.g. several scans merged into a local map), voxel-down-sampled."""
    if voxel > 0 and len(points):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
        points = np.asarray(pcd.voxel_down_sample(voxel).points)
    return Cloud(points, planar, normal_radius)


def normals_2d(xy: np.ndarray, tree: cKDTree, k: int = 7) -> np.ndarray:
    """Unit normals of planar points: the minor principal axis of their k nearest neighbours."""
    k = min(k, len(xy))
    if k < 2:
        return np.tile([1.0, 0.0], (len(xy), 1))
    _, idx = tree.query(xy, k=k)
    nb = xy[idx] - xy[idx].mean(axis=1, keepdims=True)
    sxx, syy = (nb[..., 0] ** 2).sum(1), (nb[..., 1] ** 2).sum(1)
    sxy = (nb[..., 0] * nb[..., 1]).sum(1)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy) + 0.5 * np.pi  # major axis + 90 degrees
    return np.column_stack([np.cos(angle), np.sin(angle)])


# ---- topology helpers -------------------------------------------------------------------------------

#: when an edge is found several ways, the kind recorded is the first of this order
EDGE_PRIORITY = ("loop", "external", "radius", "temporal")


def path_length(poses: np.ndarray) -> np.ndarray:
    """Distance travelled (m) up to each pose (N,4,4)."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def temporal_order(i: int, n: int):
    """Frame indices i-1, i+1, i-2, i+2, ... inside [0, n) (the official DM2 fill order)."""
    for step in range(1, n):
        if i - step >= 0:
            yield i - step
        if i + step < n:
            yield i + step
        if i - step < 0 and i + step >= n:
            return


def radius_neighbours(positions: np.ndarray, radius: float, k: int) -> list[list[int]]:
    """Up to k other frames within ``radius`` of each position, nearest first."""
    n = len(positions)
    if n < 2 or k < 1:
        return [[] for _ in range(n)]
    kk = min(k + 1, n)
    dist, idx = cKDTree(positions).query(positions, k=kk, distance_upper_bound=radius)
    dist, idx = dist.reshape(n, kk), idx.reshape(n, kk)
    inside = np.isfinite(dist) & (idx != np.arange(n)[:, None])
    return [idx[i][inside[i]][:k].tolist() for i in range(n)]


def loop_rows(
    pos: np.ndarray, path: np.ndarray, radius: float, min_gap: float, k: int, limit: int,
    looks_at: np.ndarray | None = None,
) -> list[list[tuple[int, str]]]:
    """Candidate rows for :func:`assemble`: per frame up to ``limit`` loop partners (farther than ``min_gap``
    along the path, within ``radius``, and with ``looks_at`` (N, 3) also looking at a place within ``radius``;
    nearest first), then up to ``k`` radius neighbours."""
    tree = cKDTree(pos)
    rows = []
    for i, near in enumerate(radius_neighbours(pos, radius, k)):
        loops = [j for j in tree.query_ball_point(pos[i], radius) if abs(path[j] - path[i]) > min_gap]
        if looks_at is None:
            loops.sort(key=lambda j: np.linalg.norm(pos[j] - pos[i]))
        else:
            gap = {j: np.linalg.norm(looks_at[j] - looks_at[i]) for j in loops}
            loops = [j for j in loops if gap[j] < radius]
            loops.sort(key=lambda j: np.linalg.norm(pos[j] - pos[i]) + gap[j])
        rows.append([(j, "loop") for j in loops[:limit]] + [(j, "radius") for j in near])
    return rows


def assemble(
    candidates: list[list[tuple[int, str]]], k: int, temporal: bool = True, log: list | None = None,
    successor: bool = True,
) -> Topology:
    """Topology from per-anchor (neighbour, kind) lists, best first; duplicates and the anchor itself
    dropped, then filled up with temporal neighbours to k. With ``temporal`` and ``successor`` frame i+1 is
    always in frame i's group (in place of its last candidate that is not a loop partner, or of its last loop
    partner when all are): every step is registered."""
    n = len(candidates)
    groups = np.full((n, k), -1, dtype=np.int64)
    kinds: dict[tuple[int, int], str] = {}
    for i, cand in enumerate(candidates):
        chosen: list[tuple[int, str]] = []
        seen = {i}
        for j, kind in cand:
            if j not in seen and 0 <= j < n and len(chosen) < k:
                chosen.append((j, kind))
                seen.add(j)
        if temporal and successor and i + 1 < n and i + 1 not in seen:
            if len(chosen) >= k:
                spare = [c for c, (_, kind) in enumerate(chosen) if kind != "loop"]
                seen.discard(chosen.pop(spare[-1] if spare else -1)[0])
            chosen.append((i + 1, "temporal"))
            seen.add(i + 1)
        if temporal:
            for j in temporal_order(i, n):
                if len(chosen) >= k:
                    break
                if j not in seen:
                    chosen.append((j, "temporal"))
                    seen.add(j)
        for col, (j, kind) in enumerate(chosen):
            groups[i, col] = j
            key = (min(i, j), max(i, j))
            old = kinds.get(key)
            if old is None or EDGE_PRIORITY.index(kind) < EDGE_PRIORITY.index(old):
                kinds[key] = kind
    keys = sorted(kinds)
    edges = np.array(keys, dtype=np.int64).reshape(-1, 2)
    return Topology(groups=groups, edges=edges, edge_kind=[kinds[e] for e in keys], log=list(log or []))


#: the blocks of :func:`repeatable_registration` open now (on any thread) and open3d's setting before the first
_REPEATABLE = {"open": 0, "before": 0}
_REPEATABLE_LOCK = threading.Lock()


@contextmanager
def repeatable_registration() -> Iterator[None]:
    """open3d on one thread within the block (as before it once the last block open on any thread ends): a
    registration on several of open3d's threads sums its correspondences in a different order each run, so a run's
    poses differ from the last one's in their last bits and a long sequence's drift apart. Stages that register
    many pairs run them side by side on threads of their own instead (open3d releases the GIL): the same speed,
    the same answer every run."""
    with _REPEATABLE_LOCK:
        if _REPEATABLE["open"] == 0:
            _REPEATABLE["before"] = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
        _REPEATABLE["open"] += 1
    try:
        yield
    finally:
        with _REPEATABLE_LOCK:
            _REPEATABLE["open"] -= 1
            if _REPEATABLE["open"] == 0:
                o3d.utility.set_max_threads(_REPEATABLE["before"])
