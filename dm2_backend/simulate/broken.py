"""Trajectories broken on purpose, to check what finds the break without ground truth (the consistency
profile): a jump at one frame, a jump that carries on (a front-end failure), a drifting stretch, a wrong loop
closure forced into a pose graph; and which frames each break touched."""

from __future__ import annotations

import numpy as np

from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.gtsam_solver import optimize
from dm2_backend.kernel.pose_graph import PoseGraph
from dm2_backend.kernel.trajectory import Trajectory


def bump(metres: float = 0.3, degrees: float = 2.0) -> np.ndarray:
    """A motion of ``metres`` forward and ``degrees`` of yaw (the sensor's frame)."""
    return se3.make_poses(se3.rpy_to_matrix(np.array([0.0, 0.0, np.deg2rad(degrees)])), np.array([metres, 0, 0]))


def one_frame(poses: np.ndarray, k: int, jump: np.ndarray | None = None) -> np.ndarray:
    """Frame ``k`` alone moved by ``jump`` (default :func:`bump`)."""
    out = poses.copy()
    out[k] = out[k] @ (bump() if jump is None else jump)
    return out


def jump_from(poses: np.ndarray, k: int, jump: np.ndarray | None = None) -> np.ndarray:
    """A front-end jump at frame ``k``: every later frame moved with it."""
    out = poses.copy()
    out[k:] = poses[k] @ (bump() if jump is None else jump) @ se3.relative(poses[k], poses[k:])
    return out


def drifting(poses: np.ndarray, k: int, frames: int, metres: float = 0.3, degrees: float = 2.0) -> np.ndarray:
    """From frame ``k`` a jump builds up over ``frames`` frames (a degenerate stretch), then carries on."""
    out = poses.copy()
    for j in range(k, len(poses)):
        a = min(j - k, frames) / frames
        out[j] = poses[k] @ bump(metres * a, degrees * a) @ se3.relative(poses[k], poses[j])
    return out


def closure_graph(poses: np.ndarray, i: int, j: int, error: np.ndarray, radius: float, weight: float = 10.0,
                  information: np.ndarray | None = None) -> PoseGraph:
    """The graph of ``poses`` (odometry and every pair within ``radius`` m, exact, each with ``information``,
    default identity) with one closure between ``i`` and ``j`` that is off by ``error`` and weighs ``weight``
    times the others."""
    info = np.eye(6) if information is None else information
    pos = poses[:, :3, 3]
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    pairs = [(a, b) for a in range(len(poses)) for b in range(a + 2, len(poses)) if dist[a, b] < radius]
    graph = PoseGraph.from_trajectory(Trajectory(poses))
    graph.edges = np.vstack([graph.edges, np.array(pairs + [(i, j)]).reshape(-1, 2)])
    graph.relative = np.concatenate([graph.relative, np.array([se3.relative(poses[a], poses[b]) for a, b in pairs]
                                                              ).reshape(-1, 4, 4),
                                     [se3.relative(poses[i], poses[j]) @ error]])
    graph.information = np.concatenate([np.tile(info, (len(graph.edges) - 1, 1, 1)), [weight * info]])
    return graph


def wrong_closure(poses: np.ndarray, i: int, j: int, error: np.ndarray, radius: float, weight: float = 10.0
                  ) -> np.ndarray:
    """``poses`` after gtsam solves :func:`closure_graph` (the wrong closure bends them)."""
    return optimize(closure_graph(poses, i, j, error, radius, weight)).poses


def broken_frames(truth: np.ndarray, poses: np.ndarray, tol: float = 0.01, ahead: float = 10.0) -> np.ndarray:
    """Frames whose motion from the previous frame (or to the next) differs from the truth's by over ``tol`` m
    at a point ``ahead`` m in front of the sensor (so rotation counts)."""
    point = np.array([ahead, 0.0, 0.0, 1.0])
    diff = np.linalg.norm((se3.relative(truth[:-1], truth[1:]) - se3.relative(poses[:-1], poses[1:])) @ point, axis=1)
    bad = np.zeros(len(truth), bool)
    bad[1:] |= diff > tol
    bad[:-1] |= diff > tol
    return bad


def hits_and_false_flags(flagged: np.ndarray, broken: np.ndarray, reach: int) -> tuple[bool, int]:
    """Whether a flagged frame lies within ``reach`` frames of a broken one (a hit), and how many flagged frames
    lie farther than that from every broken frame (false flags)."""
    near = np.zeros(len(broken), bool)
    for i in np.flatnonzero(broken):
        near[max(0, i - reach):i + reach + 1] = True
    return bool((flagged & near).any()), int((flagged & ~near).sum())
