"""ICP for the preparation plugins: open3d (point-to-plane, point-to-point, generalized) for 3D clouds,
and a 2D point-to-line Gauss-Newton ICP on x, y, yaw for planar laser scans, whose z-less normals leave
open3d's point-to-plane system singular."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d

from dm2_backend.algorithms.common import Cloud, Match, planar_pose, project_planar
from dm2_backend.kernel.geometry import se3

reg = o3d.pipelines.registration


def register(
    source: Cloud,
    target: Cloud,
    init: np.ndarray,
    distances: Sequence[float],
    method: str = "point-to-plane",
    iterations: int = 30,
    prior_weight: float = 0.0,
    prior_info: np.ndarray | None = None,
    tolerance: float = 1e-6,
    robust_k: float = 0.0,
    hessian: bool = False,
) -> Match:
    """Coarse-to-fine ICP of ``source`` onto ``target`` from ``init``, one pass per correspondence
    distance; fitness and rmse are those of the last (finest) distance. ``prior_weight`` (planar
    point-to-line only) keeps unconstrained directions, e.g. along a corridor, at ``init``; ``prior_info``
    (planar point-to-line only) is a full (3, 3) prior information on (x, y, yaw) about ``init``;
    ``tolerance`` (3D): a pass stops when fitness and inlier rmse change by less than this fraction;
    ``robust_k`` (planar point-to-line only): Cauchy weights on the residuals, see :func:`icp_2d`; ``hessian``:
    also the point-to-plane (planar: point-to-line) information of the result and its residuals' rms
    (``Match.hessian``)."""
    if source.planar:
        if method == "point-to-point":
            return _icp_o3d_planar(source, target, init, distances, iterations)
        return icp_2d(source.xy, target, init, distances, iterations, prior_weight=prior_weight,
                      prior_info=prior_info, robust_k=robust_k, hessian=hessian)
    T = np.asarray(init, dtype=np.float64)
    source.ensure(method, "source")
    target.ensure(method, "target")
    if method == "gicp":
        estimation = reg.TransformationEstimationForGeneralizedICP()
    elif method == "point-to-point":
        estimation = reg.TransformationEstimationPointToPoint()
    else:
        estimation = reg.TransformationEstimationPointToPlane()
    criteria = reg.ICPConvergenceCriteria(tolerance, tolerance, iterations)
    fn = reg.registration_generalized_icp if method == "gicp" else reg.registration_icp
    result = None
    for d in distances:
        result = fn(source.pcd, target.pcd, float(d), T, estimation, criteria)
        if len(result.correspondence_set) < 6:
            break
        T = np.asarray(result.transformation)
    if result is None or len(result.correspondence_set) < 6:
        return Match(T, 0.0, float("inf"))
    if not hessian:
        return Match(T.copy(), float(result.fitness), float(result.inlier_rmse))
    pairs = np.asarray(result.correspondence_set)
    normals = target_normals(target, pairs[:, 1], method)
    p = source.points[pairs[:, 0]]
    residual = np.einsum("ij,ij->i", normals, se3.transform_points(T, p) - target.points[pairs[:, 1]])
    return Match(T.copy(), float(result.fitness), float(result.inlier_rmse), point_to_plane_hessian(p, normals, T),
                 float(np.sqrt(np.mean(residual**2))))


def target_normals(target: Cloud, index: np.ndarray, method: str) -> np.ndarray:
    """Unit normals of the target points ``index``: the minor axis of their covariances where GICP built
    them, else the cloud's normals."""
    if method == "gicp":
        _, vectors = np.linalg.eigh(np.asarray(target.pcd.covariances)[index])
        return vectors[:, :, 0]
    return target.normals[index]


def point_to_plane_hessian(points: np.ndarray, normals: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The Gauss-Newton information ``J^T J`` (6, 6) of the point-to-plane residuals ``n . (T p - q)`` of
    source ``points`` (its frame) against target ``normals`` (the target's frame), on a right perturbation
    ``T Exp(xi)`` in g2o's order ``[x y z rx ry rz]``: the tangent of a pose-graph edge T_b^a (GTSAM's
    BetweenFactor). Each row is ``[m, p x m]`` with ``m = R^T n``; a direction the matched geometry does not
    pin (along a corridor, across one wall) gets no information."""
    m = np.asarray(normals, dtype=np.float64) @ np.asarray(T, dtype=np.float64)[:3, :3]
    J = np.hstack([m, np.cross(np.asarray(points, dtype=np.float64), m)])
    return J.T @ J


def _icp_o3d_planar(source: Cloud, target: Cloud, init, distances, iterations) -> Match:
    """open3d point-to-point ICP on z = 0 points (well posed), projected to x, y, yaw."""
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source.points))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
    T = project_planar(init)
    result = None
    criteria = reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations)
    for d in distances:
        p2p = reg.TransformationEstimationPointToPoint()
        result = reg.registration_icp(src, tgt, float(d), T, p2p, criteria)
        T = project_planar(np.asarray(result.transformation))
    if result is None or len(result.correspondence_set) < 3:
        return Match(T, 0.0, float("inf"))
    return Match(T, float(result.fitness), float(result.inlier_rmse))


_EPS3 = 1e-6 * np.eye(3)


def _solve3(A: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Solve a symmetric positive-definite 3x3 system by Cramer's rule (np.linalg.solve's overhead
    dominates at this size, once per ICP iteration)."""
    (a, b_, c), (_, e, f), (_, _, i) = A.tolist()
    x, y, z = b.tolist()
    co0, co1, co2 = e * i - f * f, c * f - b_ * i, b_ * f - c * e
    det = a * co0 + b_ * co1 + c * co2
    return (
        (x * co0 + y * co1 + z * co2) / det,
        (x * co1 + y * (a * i - c * c) + z * (b_ * c - a * f)) / det,
        (x * co2 + y * (b_ * c - a * f) + z * (a * e - b_ * b_)) / det,
    )


def icp_2d(
    source_xy: np.ndarray,
    target: Cloud,
    init: np.ndarray,
    distances: Sequence[float],
    iterations: int = 30,
    tol: float = 1e-3,
    prior_weight: float = 0.0,
    prior_info: np.ndarray | None = None,
    robust_k: float = 0.0,
    hessian: bool = False,
) -> Match:
    """2D point-to-line ICP (Gauss-Newton on x, y, yaw) of points onto a planar :class:`Cloud`.

    With ``robust_k`` k > 0 each step is iteratively reweighted least squares with Cauchy weights
    ``1 / (1 + (r / (k * s))^2)``, s the residuals' robust standard deviation (1.4826 x their median
    absolute value): correspondences of surfaces that only one scan sees (occlusion, the edges of the
    overlap) stop pulling the match along the direction of travel (k = 2.3849, Cauchy's 95 % efficiency).

    With ``prior_weight`` w > 0 the cost adds ``w * M * |t - t_init|^2`` (M correspondences, t the
    translation): negligible where the scan constrains the pose, decisive along directions it does
    not (a featureless corridor). ``prior_info`` (3, 3) adds ``e^T prior_info e`` with e = (x, y, yaw) - init,
    in the units of the point-to-line cost (m^2 per correspondence): e.g. odometry's information scaled by the
    residual variance, or a strong weight along one direction to hold it at ``init``.

    With ``hessian``, the match also carries its point-to-line information (3, 3) on [x y yaw] for unit residual
    variance, :func:`point_to_plane_hessian` of the last correspondences in the plane, and their residuals' rms."""
    x, y, yaw = se3.to_xy_yaw(init)
    x0, y0, yaw0 = x, y, yaw
    fitness, rmse = 0.0, float("inf")
    for pass_, d in enumerate(distances):
        # stop when an update moves points by less than tol * d (10x looser before the last pass)
        stop = tol * d * (1.0 if pass_ == len(distances) - 1 else 10.0)
        for _ in range(iterations):
            c, s = np.cos(yaw), np.sin(yaw)
            p = source_xy @ np.array([[c, s], [-s, c]]) + (x, y)
            dist, idx = target.tree.query(p, distance_upper_bound=d)
            ok = np.isfinite(dist)
            if ok.sum() < 3:
                return Match(planar_pose(x, y, yaw), 0.0, float("inf"))
            p, q, n = p[ok], target.xy[idx[ok]], target.normals[idx[ok]]
            centre = p.sum(axis=0) / len(p)
            pc = p - centre  # linearise the rotation about the centroid (well conditioned far from 0)
            r = ((p - q) * n).sum(axis=1)
            J = np.empty((len(p), 3))  # d r / d (tx, ty, theta)
            J[:, :2] = n
            J[:, 2] = n[:, 1] * pc[:, 0] - n[:, 0] * pc[:, 1]
            if robust_k > 0:
                scale = robust_k * max(1.4826 * float(np.median(np.abs(r))), 1e-9)
                w = 1.0 / (1.0 + np.square(r / scale))
                H, g = (J * w[:, None]).T @ J + _EPS3 * len(J), (J * w[:, None]).T @ r
            else:
                H, g = J.T @ J + _EPS3 * len(J), J.T @ r
            if prior_weight > 0:  # on translation only: scans rarely leave the yaw unconstrained
                Jp = np.array([[1.0, 0.0, centre[1] - y], [0.0, 1.0, x - centre[0]]])
                rp = np.array([x - x0, y - y0])
                w = prior_weight * len(J)
                H, g = H + w * Jp.T @ Jp, g + w * Jp.T @ rp
            if prior_info is not None:
                Jq = np.array([[1.0, 0.0, centre[1] - y], [0.0, 1.0, x - centre[0]], [0.0, 0.0, 1.0]])
                rq = np.array([x - x0, y - y0, se3.wrap_angle(yaw - yaw0)])
                H, g = H + Jq.T @ prior_info @ Jq, g + Jq.T @ prior_info @ rq
            dx, dy, dth = _solve3(H, -g)
            # update p' = R(dth) (p - centre) + centre + (dx, dy)
            cd, sd = np.cos(dth), np.sin(dth)
            ox, oy = x - centre[0], y - centre[1]
            x, y = cd * ox - sd * oy + centre[0] + dx, sd * ox + cd * oy + centre[1] + dy
            yaw += dth
            if np.hypot(dx, dy) + abs(dth) * np.abs(pc).max() < stop:
                break
        fitness, rmse = ok.mean(), float(np.sqrt(np.mean(dist[ok] ** 2)))
    T = planar_pose(x, y, se3.wrap_angle(yaw))
    if not hessian:
        return Match(T, float(fitness), rmse)
    return Match(T, float(fitness), rmse, *_line_information(source_xy, target, T, distances[-1]))


def _line_information(source_xy: np.ndarray, target: Cloud, T: np.ndarray,
                      distance: float) -> tuple[np.ndarray | None, float | None]:
    """Point-to-line information (3, 3) on [x y yaw] of ``source_xy`` at ``T`` against ``target`` within
    ``distance``, on a right perturbation ``T Exp(xi)`` (the planar rows and columns of
    :func:`point_to_plane_hessian`), and the rms of those residuals; (None, None) with fewer than 3
    correspondences. It is :func:`information_2d`'s (world-frame translation, yaw about the sensor) with the
    translation turned into the frame of ``T``: ``B^T info B``, B = diag(R, 1)."""
    info = information_2d(source_xy, target, T, distance)
    if info["count"] < 3:
        return None, None
    B = np.eye(3)
    B[:2, :2] = T[:2, :2]
    return B.T @ info["info"] @ B, info["line_rmse"]


def information_2d(source_xy: np.ndarray, target: Cloud, T: np.ndarray, distance: float) -> dict:
    """How well the point-to-line match of ``source_xy`` at ``T`` pins down each direction (the degeneracy
    test of a scan match), from the Gauss-Newton information J^T J over the correspondences within
    ``distance``, per correspondence:

    - ``fitness``, ``rmse``: the fraction of points with a correspondence and their rms distance;
      ``line_rmse``: the rms of their point-to-line residuals;
    - ``weak``, ``weak_axis``: the smallest eigenvalue of the translation block (the mean ``n n^T`` of the
      normals, between 0 and 1/2: near 0 along a featureless corridor) and its unit direction (world frame);
    - ``yaw``: the yaw information left once translation is free (the Schur complement, m^2: the mean squared
      lever arm of the normals' moments; near 0 inside a round room);
    - ``info``: the (3, 3) information on (x, y, yaw) (yaw about the world origin at ``T``, as ``icp_2d``'s
      prior), summed over the correspondences (divide by the residual variance for a covariance).
    """
    x, y, yaw = se3.to_xy_yaw(T)
    c, s = np.cos(yaw), np.sin(yaw)
    p = source_xy @ np.array([[c, s], [-s, c]]) + (x, y)
    dist, idx = target.tree.query(p, distance_upper_bound=distance)
    ok = np.isfinite(dist)
    out = {"fitness": float(ok.mean()) if len(ok) else 0.0, "rmse": float("inf"), "line_rmse": float("inf"),
           "weak": 0.0,
           "weak_axis": np.array([1.0, 0.0]), "yaw": 0.0, "info": np.zeros((3, 3)), "count": int(ok.sum())}
    if ok.sum() < 3:
        return out
    p, n = p[ok], target.normals[idx[ok]]
    residual = ((p - target.xy[idx[ok]]) * n).sum(axis=1)
    # about the sensor position (x, y): the same parametrisation as the prior of icp_2d
    J = np.column_stack([n, n[:, 1] * (p[:, 0] - x) - n[:, 0] * (p[:, 1] - y)])
    H = J.T @ J
    m = len(J)
    w, v = np.linalg.eigh(H[:2, :2] / m)
    schur = H[2, 2] - H[2, :2] @ np.linalg.solve(H[:2, :2] + 1e-9 * np.eye(2), H[:2, 2])
    # the prior of icp_2d uses yaw about the sensor too, so info is consistent with it
    out.update(rmse=float(np.sqrt(np.mean(dist[ok] ** 2))), line_rmse=float(np.sqrt(np.mean(residual**2))),
               weak=float(w[0]), weak_axis=v[:, 0],
               yaw=float(schur / m), info=H)
    return out


def slide_loss(source_xy: np.ndarray, target: Cloud, T: np.ndarray, step: np.ndarray, distance: float) -> float:
    """How much of the scan leaves the map when the match ``T`` slides by ``step`` = (dx, dy, dyaw) (world
    frame; yaw about the sensor), either way: the smaller increase, over the two directions, of the mean
    truncated point-to-point cost ``min(d, distance)^2 / distance^2``. About the fraction of points whose
    structure pins the match in that direction (0 along a featureless corridor, whatever the normals say)."""
    def cost(dx: float, dy: float, dyaw: float) -> float:
        x, y, yaw = se3.to_xy_yaw(T)
        c, s = np.cos(yaw + dyaw), np.sin(yaw + dyaw)
        p = source_xy @ np.array([[c, s], [-s, c]]) + (x + dx, y + dy)
        d, _ = target.tree.query(p, distance_upper_bound=distance)
        return float(np.mean(np.minimum(d, distance) ** 2)) / distance**2

    base = cost(0.0, 0.0, 0.0)
    return min(cost(*step) - base, cost(*(-np.asarray(step))) - base)
