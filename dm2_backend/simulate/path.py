"""Trajectories that revisit places (laps of a loop or a figure-eight) and drifting odometry along them."""

from __future__ import annotations

import numpy as np

from dm2_backend.kernel.geometry import se3

PATHS = ("loop", "eight")


def centerline(kind: str, radius: float, seed: int, samples: int = 4096) -> np.ndarray:
    """One lap of the street the vehicle drives, (samples, 2) closed polyline (last point != first).

    ``loop``: a wobbly circle of ``radius``; ``eight``: a figure-eight (two lobes crossing at the origin)
    ``2 radius`` wide and ``1.3 radius`` high. The wobble is drawn from ``seed``.
    """
    if kind not in PATHS:
        raise ValueError(f"unknown path {kind!r} (choose from {', '.join(PATHS)})")
    rng = np.random.default_rng([seed, 7])
    phase = rng.uniform(0, 2 * np.pi, 2)
    s = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    if kind == "loop":
        r = radius * (1 + 0.05 * np.sin(3 * s + phase[0]) + 0.025 * np.sin(5 * s + phase[1]))
        return np.stack([r * np.cos(s), r * np.sin(s)], -1)
    wobble = 1 + 0.04 * np.sin(2 * s + phase[0])
    return np.stack([radius * np.sin(s) * wobble, 0.65 * radius * np.sin(2 * s)], -1)


def street_path(kind: str, frames: int, radius: float, laps: float, seed: int) -> np.ndarray:
    """Planar poses (N,4,4) driving ``laps`` laps of :func:`centerline` at constant speed, facing forward."""
    line = centerline(kind, radius, seed)
    closed = np.vstack([line, line[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    lap = arc[-1]
    u = np.linspace(0, lap * laps, frames, endpoint=False) % lap
    xy = np.stack([np.interp(u, arc, closed[:, 0]), np.interp(u, arc, closed[:, 1])], -1)
    tangent = np.roll(closed[:-1], -1, axis=0) - np.roll(closed[:-1], 1, axis=0)
    angle = np.arctan2(tangent[:, 1], tangent[:, 0])
    heading = np.unwrap(np.append(angle, angle[0]))
    yaw = np.interp(u, arc, heading)
    return se3.from_xy_yaw(np.column_stack([xy, yaw]))


def loop_path(frames: int, radius: float, laps: float, seed: int) -> np.ndarray:
    """Laps of a wobbly circle (see :func:`street_path`)."""
    return street_path("loop", frames, radius, laps, seed)


def drifting_odometry(
    truth: np.ndarray, seed: int, yaw_sigma: float, trans_sigma: float, yaw_bias: float = 0.0,
    z_sigma: float = 0.0, tilt_sigma: float = 0.0, scale_error: float = 0.0,
) -> np.ndarray:
    """Chain the true relative motions with random-walk errors, as a wheel/LiDAR odometry would.

    Per frame: yaw noise ``yaw_sigma`` rad plus a constant ``yaw_bias`` rad (a miscalibrated gyro),
    translation noise ``trans_sigma`` x step length in x and y, and for 3D trajectories ``z_sigma`` x step
    length in z and ``tilt_sigma`` rad in roll and pitch; ``scale_error`` lengthens every step by that fraction
    (a wrong wheel radius). Errors accumulate: the drift grows along the path.
    """
    rng = np.random.default_rng(seed)
    rel = se3.relative(truth[:-1], truth[1:])
    rel[:, :3, 3] *= 1.0 + scale_error
    step = np.linalg.norm(rel[:, :3, 3], axis=1)
    noise = np.zeros((len(rel), 6))  # x y z roll pitch yaw
    noise[:, :2] = rng.normal(0, 1, (len(rel), 2)) * (trans_sigma * step)[:, None]
    noise[:, 5] = rng.normal(yaw_bias, yaw_sigma, len(rel))
    if z_sigma or tilt_sigma:
        noise[:, 2] = rng.normal(0, 1, len(rel)) * z_sigma * step
        noise[:, 3:5] = rng.normal(0, tilt_sigma, (len(rel), 2))
    errors = se3.from_xyz_euler(noise)
    out = [truth[0]]
    for R, e in zip(rel, errors):
        out.append(out[-1] @ R @ e)
    return np.stack(out)
