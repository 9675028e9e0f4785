"""An incremental SE(2) pose graph over keyframes (GTSAM iSAM2) for loop search, the pairwise cycle
check that a new closure must pass against another closure before it is trusted, and the final robust
batch solve that drops closures the rest of the graph disagrees with."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from dm2_backend.geometry import se3


def pose2(v) -> gtsam.Pose2:
    return gtsam.Pose2(float(v[0]), float(v[1]), float(v[2]))


def vec(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def between(a, b) -> np.ndarray:
    """(x, y, yaw) of b in a's frame."""
    return vec(pose2(a).between(pose2(b)))


@dataclass(eq=False)
class Closure:
    a: int  # keyframe index (earlier)
    b: int  # keyframe index (later)
    z: np.ndarray  # (x, y, yaw) of b in a's frame
    entry: dict = field(default_factory=dict)  # its record in the topology log


class KeyframeGraph:
    """Odometry chain between keyframes plus accepted closures, solved incrementally with iSAM2."""

    def __init__(self, odometry: np.ndarray, odo_sigma: np.ndarray, loop_sigma: np.ndarray) -> None:
        """``odometry`` (K, 3): keyframe poses (x, y, yaw) from the input; ``odo_sigma`` (K-1, 3) sigmas of
        each step; ``loop_sigma`` (3,) sigmas of a closure."""
        self.odometry = odometry
        self.odo_sigma = odo_sigma
        self.loop_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(1.345), gtsam.noiseModel.Diagonal.Sigmas(loop_sigma))
        self.loop_sigma = loop_sigma
        self.isam = gtsam.ISAM2(gtsam.ISAM2Params())
        self.closures: list[Closure] = []
        self.added = 0
        self.estimate = odometry.copy()

    def _prior(self) -> gtsam.PriorFactorPose2:
        """Keyframe 0 held at its input pose (fixes the gauge)."""
        return gtsam.PriorFactorPose2(0, pose2(self.odometry[0]), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6)))

    def _odometry_factor(self, k: int) -> gtsam.BetweenFactorPose2:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.maximum(self.odo_sigma[k - 1], 1e-6))
        return gtsam.BetweenFactorPose2(k - 1, k, pose2(between(self.odometry[k - 1], self.odometry[k])), noise)

    def extend(self, upto: int) -> None:
        """Add keyframes up to index ``upto`` (inclusive), chained by odometry from the current estimate."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for k in range(self.added, upto + 1):
            if k == 0:
                graph.add(self._prior())
                values.insert(0, pose2(self.odometry[0]))
            else:
                step = between(self.odometry[k - 1], self.odometry[k])
                values.insert(k, pose2(self.estimate[k - 1]).compose(pose2(step)))
                self.estimate[k] = vec(values.atPose2(k))
                graph.add(self._odometry_factor(k))
        self.added = upto + 1
        self.isam.update(graph, values)

    def close(self, closures: list[Closure]) -> None:
        """Add closures and re-solve; the estimate of every keyframe added so far is updated."""
        graph = gtsam.NonlinearFactorGraph()
        for c in closures:
            graph.add(gtsam.BetweenFactorPose2(c.a, c.b, pose2(c.z), self.loop_noise))
        self.closures += closures
        self.isam.update(graph, gtsam.Values())
        for _ in range(3):
            self.isam.update()
        est = self.isam.calculateEstimate()
        for k in range(self.added):
            self.estimate[k] = vec(est.atPose2(k))

    def solve_batch(self, gate: float) -> tuple[np.ndarray, list[Closure], list[Closure]]:
        """Levenberg-Marquardt on the whole graph; closures whose whitened error exceeds ``gate`` (sigmas)
        after the solve are dropped one at a time (worst first) and the graph re-solved. Returns the
        keyframe poses, the kept and the dropped closures."""
        kept, dropped = list(self.closures), []
        while True:
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            graph.add(self._prior())
            for k in range(len(self.odometry)):
                values.insert(k, pose2(self.estimate[k]))
                if k:
                    graph.add(self._odometry_factor(k))
            plain = gtsam.noiseModel.Diagonal.Sigmas(self.loop_sigma)
            for c in kept:
                graph.add(gtsam.BetweenFactorPose2(c.a, c.b, pose2(c.z), plain))
            result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
            poses = np.array([vec(result.atPose2(k)) for k in range(len(self.odometry))])
            errors = [closure_error(poses, c, self.loop_sigma) for c in kept]
            if not kept or max(errors) <= gate:
                return poses, kept, dropped
            dropped.append(kept.pop(int(np.argmax(errors))))


def closure_error(poses: np.ndarray, c: Closure, sigma: np.ndarray) -> float:
    """Whitened norm of the closure's residual at ``poses``."""
    r = between(poses[c.a], poses[c.b]) - c.z
    r[2] = se3.wrap_angle(r[2])
    return float(np.linalg.norm(r / sigma))


def cycle_error(odometry: np.ndarray, c1: Closure, c2: Closure) -> tuple[float, float]:
    """Translation (m) and rotation (rad) error of the cycle a1 -> b1 -> b2 -> a2 -> a1 formed by two
    closures and the odometry between their ends: zero when both closures agree."""
    via = pose2(c1.z).compose(pose2(between(odometry[c1.b], odometry[c2.b])))
    other = pose2(between(odometry[c1.a], odometry[c2.a])).compose(pose2(c2.z))
    e = via.between(other)
    return float(np.hypot(e.x(), e.y())), abs(float(e.theta()))
