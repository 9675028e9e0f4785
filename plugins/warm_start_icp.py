"""Warm start ``icp``: incremental scan-to-local-map ICP (open3d GICP by default in 3D, 2D point-to-line
for planar scans), predicted by constant velocity or by the given trajectory's increments.

Each frame is registered onto a local map: the points of the last ``window`` keyframes in the world
frame, voxel-down-sampled. The prediction T_{i-1} @ delta (delta: the last increment, or the given
trajectory's) starts a coarse-to-fine ICP; T_i is its result (projected to x, y, yaw for planar data),
or the prediction when the fitness is too low."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.errors import InputError
from dm2_backend.geometry import se3
from dm2_backend.plugins.common import (
    Cloud,
    fine_distance,
    lengths,
    orthonormal,
    project_planar,
    resolve_method,
    rotation_angle,
    voxel_cloud,
)
from dm2_backend.plugins.icp import register
from dm2_backend.prepare.types import Frames
from dm2_backend.progress import progress
from dm2_backend.trajectory import Trajectory


@dataclass
class IcpWarmStart:
    """Options; None means derived from the data (``Frames.scale``)."""

    name: ClassVar[str] = "icp"

    #: "auto" (GICP in 3D, 2D point-to-line for planar scans), "point-to-plane", "point-to-point", "gicp"
    method: str = "auto"
    #: fine correspondence distance (m); default 3 point spacings; the coarse pass uses 4x this
    max_distance: float | None = None
    #: keyframes kept in the local map
    window: int = 10
    #: a new keyframe after this translation (m; default range_median / 10) or rotation (degrees)
    keyframe_distance: float | None = None
    keyframe_angle: float = 10.0
    #: map voxel (m); default the frames' voxel or point spacing
    map_voxel: float | None = None
    #: prediction: "velocity" (constant velocity), "given" (increments of the given trajectory) or "auto"
    prior: str = "auto"
    #: below this fitness the registration is rejected and the prediction kept
    min_fitness: float = 0.3
    #: (velocity prior) below this fitness ICP is also tried from the previous pose
    retry_fitness: float = 0.6
    iterations: int = 30
    #: (planar) weight of the prediction against the scan, per correspondence: keeps the motion along
    #: directions the scan does not constrain (corridors)
    prior_weight: float = 0.01
    progress: bool = True

    def run(self, frames: Frames, given: Trajectory | None) -> np.ndarray:
        method = resolve_method(self.method, frames.planar)
        scale = lengths(frames)
        fine = self.max_distance or fine_distance(scale)
        distances = (4.0 * fine, fine)
        kf_dist = self.keyframe_distance or scale["range_median"] / 10.0
        kf_angle = np.radians(self.keyframe_angle)
        voxel = self.map_voxel or max(scale["voxel"], scale["spacing"])
        increments = self._increments(frames, given)
        n = len(frames)
        poses = np.tile(np.eye(4), (n, 1, 1))
        if given is not None:
            poses[0] = project_planar(given.poses[0]) if frames.planar else given.poses[0]
        keyframes: deque[np.ndarray] = deque(maxlen=self.window)
        keyframes.append(se3.transform_points(poses[0], frames.points[0].astype(np.float64)))
        last_key = poses[0]
        target = self._map(keyframes, frames.planar, voxel, fine)
        velocity = np.eye(4)
        self.rejected: list[int] = []
        for i in progress(range(1, n), "icp warm start", unit="frame", enabled=self.progress):
            delta = increments[i - 1] if increments is not None else velocity
            predicted = poses[i - 1] @ delta
            source = Cloud(frames.points[i], frames.planar, 2.0 * fine)
            match = register(source, target, predicted, distances, method, self.iterations, self.prior_weight)
            if increments is None and match.fitness < self.retry_fitness:
                # constant velocity may overshoot a stop: also try standing still, keep it if clearly better
                still = register(source, target, poses[i - 1], distances, method, self.iterations, self.prior_weight)
                if still.fitness > match.fitness + 0.1:
                    match = still
            if match.fitness >= self.min_fitness and np.isfinite(match.T).all():
                poses[i] = project_planar(match.T) if frames.planar else orthonormal(match.T)
            else:
                poses[i] = predicted
                self.rejected.append(i)
            velocity = se3.relative(poses[i - 1], poses[i])
            moved = se3.relative(last_key, poses[i])
            if np.linalg.norm(moved[:3, 3]) > kf_dist or rotation_angle(moved[:3, :3]) > kf_angle:
                keyframes.append(se3.transform_points(poses[i], source.points))
                last_key = poses[i]
                target = self._map(keyframes, frames.planar, voxel, fine)
        return poses

    def _increments(self, frames: Frames, given: Trajectory | None) -> np.ndarray | None:
        if self.prior not in ("auto", "velocity", "given"):
            raise InputError(None, f"icp warm start: unknown prior {self.prior!r} (auto, velocity, given)")
        if self.prior == "velocity" or (self.prior == "auto" and given is None):
            return None
        if given is None:
            raise InputError(None, "icp warm start: prior 'given' needs a trajectory")
        if len(given) != len(frames):
            raise InputError(None, f"icp warm start: {len(given)} poses for {len(frames)} frames")
        return se3.relative(given.poses[:-1], given.poses[1:])

    @staticmethod
    def _map(keyframes: deque, planar: bool, voxel: float, fine: float) -> Cloud:
        return voxel_cloud(np.concatenate(list(keyframes)), voxel, planar, 2.0 * fine)
