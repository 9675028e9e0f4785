"""An incremental SE(2) pose graph over keyframes (GTSAM iSAM2) for loop search, the pairwise cycle
check that a new closure must pass against another closure before it is trusted, and the final robust
batch solve that drops closures the rest of the graph disagrees with.

A closure across a corridor (``Closure.axis``: the direction, in keyframe a's frame, along which its match
was ambiguous) constrains only the other translation direction and yaw: its factor carries almost no
information along the axis, and cycle checks and residuals leave that component out."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from dm2_backend.kernel.geometry import se3


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
    weak: bool = False  # needs more agreement before it is trusted: a narrow overlap, or across a corridor
    axis: np.ndarray | None = None  # (2,) unit direction in a's frame that the closure leaves free (a corridor)


def confirms(new: Closure, agreeing: list[Closure]) -> bool:
    """Whether the closures that agree with ``new`` around a cycle are enough to trust it: any one, for a
    closure that passed every gate; for a weak one (narrow overlap, or across a corridor), one that passed
    every gate or two weak ones."""
    support = sum(0.5 if c.weak else 1.0 for c in agreeing)
    return support >= (1.0 if new.weak else 0.5)


class KeyframeGraph:
    """Odometry chain between keyframes plus accepted closures, solved incrementally with iSAM2."""

    def __init__(self, odometry: np.ndarray, odo_sigma: np.ndarray, loop_sigma: np.ndarray) -> None:
        """``odometry`` (K, 3): keyframe poses (x, y, yaw) from the input; ``odo_sigma`` (K-1, 3) sigmas of
        each step; ``loop_sigma`` (3,) sigmas of a closure."""
        self.odometry = odometry
        self.odo_sigma = odo_sigma
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
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                                   closure_noise(c, self.loop_sigma))
            graph.add(gtsam.BetweenFactorPose2(c.a, c.b, pose2(c.z), noise))
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
            for c in kept:
                graph.add(gtsam.BetweenFactorPose2(c.a, c.b, pose2(c.z), closure_noise(c, self.loop_sigma)))
            result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
            poses = np.array([vec(result.atPose2(k)) for k in range(len(self.odometry))])
            errors = [closure_error(poses, c, self.loop_sigma) for c in kept]
            if not kept or max(errors) <= gate:
                return poses, kept, dropped
            dropped.append(kept.pop(int(np.argmax(errors))))


#: two corridor closures whose free axes differ by more than this (degrees) cannot check each other
CROSSING_DEG = 20.0
#: sigma along a corridor closure's free axis, in multiples of its translation sigma: effectively unconstrained
FREE_AXIS_SCALE = 1e4


def closure_noise(c: Closure, sigma: np.ndarray) -> gtsam.noiseModel.Base:
    """Diagonal ``sigma`` (x, y, yaw); for a corridor closure, ``sigma[0]`` across its axis and
    ``FREE_AXIS_SCALE`` times that along it, expressed in the factor's residual frame (the measured pose's)."""
    if c.axis is None:
        return gtsam.noiseModel.Diagonal.Sigmas(sigma)
    cz, sz = np.cos(c.z[2]), np.sin(c.z[2])
    v = np.array([cz * c.axis[0] + sz * c.axis[1], -sz * c.axis[0] + cz * c.axis[1]])  # R(z)^T axis
    n = np.array([-v[1], v[0]])
    info = np.zeros((3, 3))
    info[:2, :2] = np.outer(n, n) / sigma[0] ** 2 + np.outer(v, v) / (FREE_AXIS_SCALE * sigma[0]) ** 2
    info[2, 2] = 1.0 / sigma[2] ** 2
    return gtsam.noiseModel.Gaussian.Information(info)


def _drop_free(d: np.ndarray, axes: list[np.ndarray]) -> np.ndarray:
    """``d`` (2,) without its components along ``axes`` (unit vectors); an axis within ``CROSSING_DEG`` of one
    already dropped counts as parallel to it and adds nothing (:func:`cycle_error` refuses axes that cross)."""
    basis: list[np.ndarray] = []
    for u in axes:
        for b in basis:
            u = u - (u @ b) * b
        if np.linalg.norm(u) > np.sin(np.radians(CROSSING_DEG)):
            basis.append(u / np.linalg.norm(u))
    for b in basis:
        d = d - (d @ b) * b
    return d


def closure_error(poses: np.ndarray, c: Closure, sigma: np.ndarray) -> float:
    """Whitened norm of the closure's residual at ``poses`` (without the free axis of a corridor closure)."""
    r = between(poses[c.a], poses[c.b]) - c.z
    r[2] = se3.wrap_angle(r[2])
    if c.axis is not None:
        r[:2] = _drop_free(r[:2], [c.axis])
    return float(np.linalg.norm(r / sigma))


def _rotate(yaw: float, u: np.ndarray) -> np.ndarray:
    return np.array([np.cos(yaw) * u[0] - np.sin(yaw) * u[1], np.sin(yaw) * u[0] + np.cos(yaw) * u[1]])


def cycle_error(odometry: np.ndarray, c1: Closure, c2: Closure) -> tuple[float, float]:
    """Translation (m) and rotation (rad) error of the cycle a1 -> b1 -> b2 -> a2 -> a1 formed by two
    closures and the odometry between their ends: zero when both closures agree. The translation error
    leaves out the free axis of a corridor closure; two corridor closures whose axes cross (by more than
    ``CROSSING_DEG``) cannot check each other's translation: infinite error."""
    via = pose2(c1.z).compose(pose2(between(odometry[c1.b], odometry[c2.b])))  # b2 in a1's frame, through c1
    a2 = pose2(between(odometry[c1.a], odometry[c2.a]))
    other = a2.compose(pose2(c2.z))  # the same, through c2
    d = np.array([other.x() - via.x(), other.y() - via.y()])
    axes = [c1.axis] if c1.axis is not None else []
    if c2.axis is not None:
        axes.append(_rotate(a2.theta(), c2.axis))
    turn = abs(float(se3.wrap_angle(other.theta() - via.theta())))
    if len(axes) == 2 and abs(axes[0][0] * axes[1][1] - axes[0][1] * axes[1][0]) > np.sin(np.radians(CROSSING_DEG)):
        return float("inf"), turn
    return float(np.linalg.norm(_drop_free(d, axes))), turn
