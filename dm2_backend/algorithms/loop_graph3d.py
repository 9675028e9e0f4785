"""A batch SE(3) pose graph over every frame (GTSAM Levenberg-Marquardt): the input trajectory's
increments as odometry, loop closures between keyframes, and a robust pass that drops the closures the
rest of the graph disagrees with."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from dm2_backend.kernel.geometry import se3


@dataclass(eq=False)
class Closure3:
    i: int  # frame index (earlier)
    j: int  # frame index (later)
    z: np.ndarray  # (4, 4) pose of frame j in frame i
    entry: dict = field(default_factory=dict)  # its record in the topology log


def _sigmas(translation: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """GTSAM Pose3 order: rotation first, then translation."""
    return np.concatenate([rotation, translation])


class FrameGraph:
    """Odometry chain over all frames plus loop closures; ``solve`` returns the corrected poses."""

    def __init__(self, poses: np.ndarray, odo_t: np.ndarray, odo_r: np.ndarray, loop_t: float, loop_r: float):
        """``poses`` (N,4,4) the input trajectory; ``odo_t``/``odo_r`` (N-1,) sigmas (m, rad) of each step;
        ``loop_t``/``loop_r`` the sigmas of a closure."""
        self.poses = poses
        self.odometry = se3.relative(poses[:-1], poses[1:])
        self.odo_sigma = [np.maximum(_sigmas(np.full(3, t), np.full(3, r)), 1e-9) for t, r in zip(odo_t, odo_r)]
        self.loop_sigma = _sigmas(np.full(3, loop_t), np.full(3, loop_r))

    def _graph(self, closures: list[Closure3]) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(self.poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        for k, (rel, sigma) in enumerate(zip(self.odometry, self.odo_sigma)):
            graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(rel), gtsam.noiseModel.Diagonal.Sigmas(sigma)))
        huber = gtsam.noiseModel.mEstimator.Huber.Create(1.345)
        for c in closures:
            noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(self.loop_sigma))
            graph.add(gtsam.BetweenFactorPose3(c.i, c.j, gtsam.Pose3(c.z), noise))
        return graph

    def solve(self, closures: list[Closure3], gate: float) -> tuple[np.ndarray, list[Closure3], list[Closure3]]:
        """Levenberg-Marquardt from the input poses; closures whose whitened residual
        exceeds ``gate`` are dropped one at a time (worst first) and the graph re-solved. Returns the poses,
        the kept and the dropped closures."""
        kept, dropped = list(closures), []
        while True:
            values = gtsam.Values()
            for k, T in enumerate(self.poses):
                values.insert(k, gtsam.Pose3(T))
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(50)
            result = gtsam.LevenbergMarquardtOptimizer(self._graph(kept), values, params).optimize()
            poses = np.array([result.atPose3(k).matrix() for k in range(len(self.poses))])
            errors = [self.residual(poses, c) for c in kept]
            if not kept or max(errors) <= gate:
                return poses, kept, dropped
            dropped.append(kept.pop(int(np.argmax(errors))))

    def residual(self, poses: np.ndarray, c: Closure3) -> float:
        """Whitened norm of a closure's residual at ``poses``."""
        e = se3.relative(c.z, se3.relative(poses[c.i], poses[c.j]))
        r = _sigmas(e[:3, 3], se3.log_so3(e[:3, :3]))
        return float(np.linalg.norm(r / self.loop_sigma))
