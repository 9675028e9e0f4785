"""Trajectories that revisit places (laps of a loop) and drifting odometry computed from them."""

from __future__ import annotations

import numpy as np

from dm2_backend.geometry import se3


def loop_path(frames: int, radius: float, laps: float, seed: int, wiggle: float = 0.05) -> np.ndarray:
    """Planar poses (N,4,4) driving ``laps`` times around a wobbly circle, heading along the path."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2 * np.pi * laps, frames, endpoint=False)
    phase = rng.uniform(0, 2 * np.pi, 3)
    r = radius * (1 + wiggle * np.sin(3 * s + phase[0]) + 0.5 * wiggle * np.sin(5 * s + phase[1]))
    xy = np.stack([r * np.cos(s), r * np.sin(s)], -1)
    d = np.gradient(xy, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    return se3.from_xy_yaw(np.column_stack([xy, yaw]))


def drifting_odometry(
    truth: np.ndarray, seed: int, yaw_sigma: float, trans_sigma: float, yaw_bias: float = 0.0
) -> np.ndarray:
    """Chain the true relative motions with random-walk errors in yaw and translation (per frame:
    yaw noise ``yaw_sigma`` rad + ``yaw_bias`` rad, translation noise ``trans_sigma`` x step length)."""
    rng = np.random.default_rng(seed)
    rel = se3.relative(truth[:-1], truth[1:])
    step = np.linalg.norm(rel[:, :3, 3], axis=1)
    noise = np.zeros((len(rel), 3))
    noise[:, :2] = rng.normal(0, 1, (len(rel), 2)) * (trans_sigma * step)[:, None]
    noise[:, 2] = rng.normal(yaw_bias, yaw_sigma, len(rel))
    out = [truth[0]]
    for R, e in zip(rel, se3.from_xy_yaw(noise)):
        out.append(out[-1] @ R @ e)
    return np.stack(out)
