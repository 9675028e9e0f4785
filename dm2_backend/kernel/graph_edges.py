"""Build a pose graph from the preparation results (warm start, topology, pairwise registrations).

Edges (``(i, j)``, i < j, the pose of frame j in frame i):

* odometry ``(i, i+1)`` for every consecutive pair: by default the relative pose ``inv(T_i) @ T_{i+1}`` of
  the initial trajectory (the front end's, or its loop-closed correction, which keeps it locally; scan-to-map
  odometry is locally more accurate than
  scan-to-scan registration: docs/decisions/0009-registration-and-pose-graph-defaults.md);
  with ``odometry="registration"`` the pairwise registration when ``(i, i+1)`` is a valid topology pair,
  else the front end's;
* loop: every other valid pairwise registration, once per unordered pair.

Information model (default; a registration without a Hessian; :func:`registration_information`):
a registration with inlier rmse ``r``, overlap ``fitness`` of the neighbour's ``M`` points and lever arm ``L``
(rms range of the neighbour's points) gets isotropic ``sigma_t = max(r, floor) / sqrt(fitness * M)`` and
``sigma_r = sigma_t / L``. With :attr:`InformationModel.use_hessians` (the pose graphs: when
``registration.options.information: hessian`` asks; the dense stage: always, on the Hessians every planar
registration records), a registration's information is its
own Gauss-Newton Hessian in point-to-plane (planar: point-to-line) form over its correspondences divided by the
variance of those residuals, ``J^T J / max(r_plane, floor)^2`` (:func:`hessian_information`), so a direction the
matched geometry does not pin (along a corridor, across the one wall a camera sees) carries no weight and stays
where the odometry puts it. Front-end odometry edges get the median isotropic registration information times
``fallback_weight``.

Information matrices are tangent-space (GTSAM semantics, as ``gtsam.readG2o`` reads them) in g2o order:
``[x y z rx ry rz]`` (3D) or ``[x y theta]`` (planar data -> SE2 graph).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.pose_graph import GraphBuild, PoseGraph
from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.runtime.errors import InputError

MODEL_TEXT = "sigma_t = max(rmse, floor) / sqrt(fitness * points), sigma_r = sigma_t / lever arm"
HESSIAN_TEXT = "registration Hessian J^T J (point-to-plane) / max(plane rmse, floor)^2; odometry: " + MODEL_TEXT
#: added to a Hessian information's diagonal, relative to the mean of its translation (rotation) diagonal (see
#: :func:`hessian_information`)
EIGEN_FLOOR = 1e-6


@dataclass
class InformationModel:
    #: lower bound on the inlier rmse (m); default 0.1 * max(voxel, point spacing)
    rmse_floor: float | None = None
    #: front-end odometry edges: median registration information times this
    fallback_weight: float = 1.0
    #: "front-end" (relative poses of the initial trajectory) or "registration" (see the module docstring)
    odometry: str = "front-end"
    #: weigh a registration by its own Hessian where the preparation recorded one (else isotropic)
    use_hessians: bool = False

    @classmethod
    def from_resolved(cls, resolved: dict) -> InformationModel:
        """The model ``registration.options.information`` asks for, from a preparation's resolved plugins."""
        registration = resolved.get("registration")
        options = registration.options if registration is not None else {}
        return cls(use_hessians=options.get("information") == "hessian")


@dataclass
class PairEdge:
    """One valid registration of frame b onto frame a (a < b)."""

    relative: np.ndarray  # T_b^a
    fitness: float
    rmse: float
    points: int  # points of the registered (neighbour) frame
    hessian: np.ndarray | None = None  # (6, 6), planar (3, 3): this registration's J^T J (g2o order), if any
    plane_rmse: float = float("inf")  # rms of its point-to-plane residuals (m), with ``hessian``


def valid_pairs(topology: Topology, pairwise: Pairwise, frames: Frames) -> dict[tuple[int, int], PairEdge]:
    """Valid registrations keyed by (a, b), a < b; of (i, j) and (j, i) the lower-rmse one is kept."""
    groups = np.asarray(topology.groups)
    out: dict[tuple[int, int], PairEdge] = {}
    for i, n in zip(*np.nonzero((groups >= 0) & pairwise.valid), strict=True):
        j = int(groups[i, n])
        i = int(i)
        if i == j:
            continue
        a, b = min(i, j), max(i, j)
        T = pairwise.relative[i, n] if i == a else se3.inverse(pairwise.relative[i, n])
        H = None if pairwise.hessian is None else np.asarray(pairwise.hessian[i, n], dtype=np.float64)
        has = H is not None and bool(np.any(H))
        edge = PairEdge(T, float(pairwise.fitness[i, n]), float(pairwise.rmse[i, n]), len(frames.points[j]),
                        H if has else None, float(pairwise.plane_rmse[i, n]) if has else float("inf"))
        if (a, b) not in out or edge.rmse < out[(a, b)].rmse:
            out[(a, b)] = edge
    return out


def lever_arms(frames: Frames) -> np.ndarray:
    """Rms range (m) of each frame's points (x, y only when planar); at least 1e-3."""
    dims = 2 if frames.planar else 3
    arms = [np.sqrt((p[:, :dims].astype(np.float64) ** 2).sum(1).mean()) if len(p) else 0.0
            for p in frames.points]
    return np.maximum(np.asarray(arms), 1e-3)


def rmse_floor(frames: Frames, model: InformationModel) -> float:
    if model.rmse_floor is not None:
        return model.rmse_floor
    s = frames.scale
    base = max(s.voxel or 0.0, s.spacing or 0.0)
    return 0.1 * base if base > 0 else 1e-3


def residual_sigma(rmse: float, floor: float) -> float:
    """A registration's residual scale (m): its rmse, at least ``floor`` (the floor where it is not finite)."""
    return max(rmse if np.isfinite(rmse) else floor, floor)


def registration_information(rmse: float, fitness: float, points: int, lever: float, planar: bool,
                             floor: float) -> np.ndarray:
    """Diagonal information of one registration: ``sigma_t = max(rmse, floor) / sqrt(fitness * points)``
    (standard error of the mean inlier residual), ``sigma_r = sigma_t / lever`` (rad)."""
    inliers = max(fitness * points, 1.0)
    sigma_t = residual_sigma(rmse, floor) / np.sqrt(inliers)
    sigma_r = sigma_t / lever
    sig = [sigma_t, sigma_t, sigma_r] if planar else [sigma_t] * 3 + [sigma_r] * 3
    return np.diag(1.0 / np.square(sig))


def hessian_information(hessian: np.ndarray, rmse: float, floor: float) -> np.ndarray:
    """Information of one registration from its point-to-plane Hessian (unit residual variance) and the rms of
    its point-to-plane residuals: ``hessian / max(rmse, floor)^2``, plus :data:`EIGEN_FLOOR` of the mean
    translation (rotation) diagonal on the translation (rotation) diagonal, so a direction the registration
    does not see keeps a negligible weight in its own units and GTSAM gets a positive definite matrix."""
    sigma = residual_sigma(rmse, floor)
    info = 0.5 * (hessian + hessian.T) / sigma**2
    d = np.diag(info)
    t = 2 if len(d) == 3 else 3  # planar [x y theta] or [x y z rx ry rz]
    floors = [max(d[:t].mean(), 1e-300)] * t + [max(d[t:].mean(), 1e-300)] * (len(d) - t)
    return info + np.diag(EIGEN_FLOOR * np.asarray(floors))


def build_graph(frames: Frames, warm: np.ndarray, topology: Topology, pairwise: Pairwise,
                model: InformationModel | None = None) -> PoseGraph:
    """The pose graph of module docstring; node ids 0..N-1, initial poses = warm start."""
    model = model or InformationModel()
    if model.odometry not in ("front-end", "registration"):
        raise InputError(None, f"graph odometry must be front-end or registration, got {model.odometry!r}")
    planar = frames.planar
    n = len(warm)
    poses = se3.from_xy_yaw(se3.to_xy_yaw(warm)) if planar else np.asarray(warm, dtype=np.float64)
    pairs = valid_pairs(topology, pairwise, frames)
    arms, floor = lever_arms(frames), rmse_floor(frames, model)
    isotropic = {p: registration_information(e.rmse, e.fitness, e.points, arms[p[1]], planar, floor)
                 for p, e in pairs.items()}
    info = {p: hessian_information(e.hessian, e.plane_rmse, floor) if model.use_hessians and e.hessian is not None
            else isotropic[p] for p, e in pairs.items()}
    hessians = sum(1 for e in pairs.values() if model.use_hessians and e.hessian is not None)
    if info:
        fallback = np.median(np.stack(list(isotropic.values())), axis=0) * model.fallback_weight
    else:
        sigma = max(frames.scale.voxel or 0.0, frames.scale.spacing or 0.0) or 0.1
        fallback = registration_information(sigma, 1.0, 1, float(np.median(arms)), planar, floor)
    edges, relative, information = [], [], []
    warm_odometry = 0
    for i in range(n - 1):
        e = pairs.get((i, i + 1)) if model.odometry == "registration" else None
        edges.append((i, i + 1))
        if e is not None:
            relative.append(e.relative)
            information.append(info[(i, i + 1)])
        else:
            relative.append(se3.relative(poses[i], poses[i + 1]))
            information.append(fallback)
            warm_odometry += 1
    loops = sorted(p for p in pairs if p[1] - p[0] > 1)
    for p in loops:
        edges.append(p)
        relative.append(pairs[p].relative)
        information.append(info[p])
    relative = np.asarray(relative, dtype=np.float64).reshape(-1, 4, 4)
    if planar:
        relative = se3.from_xy_yaw(se3.to_xy_yaw(relative)).reshape(-1, 4, 4)
    dim = 3 if planar else 6
    return PoseGraph(
        ids=np.arange(n), poses=poses.reshape(-1, 4, 4), edges=np.asarray(edges, dtype=int).reshape(-1, 2),
        relative=relative, information=np.asarray(information).reshape(-1, dim, dim), planar=planar,
        built=GraphBuild(n - 1, warm_odometry, len(loops), floor, HESSIAN_TEXT if hessians else MODEL_TEXT,
                         hessians),
    )
