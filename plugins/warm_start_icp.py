"""Warm start ``icp``: incremental scan-to-local-map ICP (open3d GICP by default in 3D, 2D point-to-line
for planar scans), predicted by constant velocity or by the given trajectory's increments.

Each frame is registered onto a local map: the points of the last ``window`` keyframes in the world
frame, voxel-down-sampled. The prediction T_{i-1} @ delta (delta: the last increment, or the given
trajectory's) starts a coarse-to-fine ICP; T_i is its result (projected to x, y, yaw for planar data),
or the prediction when the fitness is too low.

By default (``fuse: auto``), planar scans with a given trajectory (the wheel odometry a CARMEN log carries, or
``--poses``) fuse the two per step (``fuse: off``: plain ICP from the odometry's prediction): the
odometry increment is the initial guess and a prior, and each scan match passes a degeneracy test before
it replaces the odometry (:meth:`IcpWarmStart._fused_step`):

- overlap: at least ``min_fitness`` of the scan's points within the fine distance of the map;
- conditioning: the weakest translation direction of the point-to-line information (the smallest
  eigenvalue of the mean ``n n^T``, 0 along a featureless corridor, 1/2 when walls face every way) and the
  yaw information left once translation is free; a direction below ``min_constraint`` is taken from the
  odometry (the ICP is re-run with that direction held at the prediction) and the others from the scan;
- agreement: a match that departs from the odometry increment by more than the gate (``gate`` robust
  standard deviations of the recent scan-vs-odometry differences, at least one fine distance / its angle
  at the median range) is kept only when it lays the scan onto the previous scan clearly better than the
  prediction (the local map holds the last steps, which a sliding match bends) and does not carry the robot
  farther than the odometry moved by more than the odometry's noise allows (an odometry glitch: a wheel slips,
  a gyro jumps); otherwise the odometry increment is used (a scan-matching failure).

The scan matching's own match cycles (:mod:`dm2_backend.algorithms.match_noise`) measure how precise it is against the
odometry; by default (``weigh: auto``) a log whose odometry they find the more precise source on every axis has its
scan matches weighed against the odometry per axis by them (as ``weigh: cycles``), any other log takes them whole
(``weigh: whole``): docs/decisions/0015-scan-weights-from-match-cycles.md.

Then the steps are checked where drift shows (``windows``, :mod:`dm2_backend.algorithms.drift_windows`): over
windows one median scan range long, the warm start's relative pose is compared with the odometry's; a
disagreement beyond what the odometry's noise (estimated from the per-step differences) explains is judged by the
window's end scans, and the odometry's increments replace the window's where they lay those scans clearly
better (scan matching that drifted, e.g. biased by returns that are not surfaces). Why these defaults:
docs/decisions/0010-fused-warm-start-windows.md.

``report`` (after ``run``) holds the counts, a per-step record (source and reason) and a per-window record
(:class:`~dm2_backend.algorithms.drift_windows.WindowVerdict`, also in ``windows``), which the run folder writes
as ``warm_start.json``."""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from dm2_backend.algorithms.common import (
    Cloud,
    fine_distance,
    lengths,
    orthonormal,
    project_planar,
    resolve_method,
    rotation_angle,
    voxel_cloud,
)
from dm2_backend.algorithms.drift_windows import OdometryNoise, WindowVerdict, apply_verdicts, check_windows
from dm2_backend.algorithms.icp import information_2d, register, slide_loss
from dm2_backend.algorithms.match_noise import AXES, MIN_TRIPLES, MatchWeights, match_weights
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.prepared import Frames
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.progress import progress


class StepReason(enum.Enum):
    """Why a warm-start step took the odometry, whole or in part; the value is what the report counts."""

    OVERLAP = "overlap"
    DEGENERATE = "degenerate in translation and yaw"
    DIVERGED = "ICP diverged"
    DISAGREES = "disagrees with the odometry"
    GLITCH = "odometry glitch"
    FARTHER = "farther than the odometry moved"
    TRANSLATION = "translation degenerate"
    YAW = "yaw degenerate"

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
    #: a new keyframe also after this rotation since the last keyframe (degrees); see ``keyframe_distance``
    keyframe_angle: float = 10.0
    #: map voxel (m); default the frames' voxel or point spacing
    map_voxel: float | None = None
    #: prediction: "velocity" (constant velocity), "given" (increments of the given trajectory) or "auto"
    prior: str = "auto"
    #: below this fitness the registration is rejected and the prediction kept
    min_fitness: float = 0.3
    #: (velocity prior) below this fitness ICP is also tried from the previous pose
    retry_fitness: float = 0.6
    #: at most this many ICP iterations per correspondence-distance pass (the coarse pass, then the fine one)
    iterations: int = 30
    #: (planar) weight of the prediction against the scan, per correspondence: keeps the motion along
    #: directions the scan does not constrain (corridors)
    prior_weight: float = 0.01
    #: planar scans with a given trajectory: fuse scan matching with its increments and test each match
    #: for degeneracy ("auto": when the given increments are the prediction; "off": plain ICP as above)
    fuse: str = "auto"
    #: (fuse) a direction (the weakest translation direction of the match's information, or yaw) comes from
    #: the odometry when sliding the match one fine distance along it (a turn moving points at the median
    #: range as far) moves less than this share of the scan off the map
    min_constraint: float = 0.1
    #: (fuse) a match departing from the odometry by more than this many robust standard deviations of the
    #: recent scan-vs-odometry differences must fit the map clearly better than the prediction to be kept
    gate: float = 6.0
    #: (fuse) "clearly better": at least this much more of the scan within the fine distance of the map
    better_fitness: float = 0.1
    #: (fuse) check the steps against the odometry over windows of path and fall back to the odometry's
    #: increments where scan matching drifted ("auto"; "off": per-step tests only)
    windows: str = "auto"
    #: (fuse) "whole": scan matches are taken whole; "cycles": each is weighed against the odometry per axis by how
    #: much of its disagreement with the odometry the scan matching's own inconsistency explains (measured on match
    #: cycles, :mod:`dm2_backend.algorithms.match_noise`), the window check's odometry noise is that share and an
    #: undecidable window takes the more precise source; "auto": "cycles" where the cycles find the odometry the
    #: more precise source on every axis, else "whole" (docs/decisions/0015-scan-weights-from-match-cycles.md)
    weigh: str = "auto"
    #: report the stage's progress: a bar on a terminal, else one INFO log line when it ends; false: silent
    progress: bool = True

    def run(self, frames: Frames, given: Trajectory | None) -> np.ndarray:
        method = resolve_method(self.method, frames.planar)
        scale = lengths(frames)
        fine = self.max_distance or fine_distance(scale)
        distances = (4.0 * fine, fine)
        kf_dist = self.keyframe_distance or scale.range_median / 10.0
        kf_angle = np.radians(self.keyframe_angle)
        voxel = self.map_voxel or max(scale.voxel, scale.spacing)
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
        #: (fused) the verdict of every window of path, after ``run``
        self.verdicts: list[WindowVerdict] = []
        fuse = self._fusing(frames, increments, method)
        if fuse:
            self._start_fusion(n, fine, scale.range_median)
            self._weights = self._match_weights(frames, given, fine)
        #: (fused) the last scan, against which a large departure from the odometry is judged
        self._previous_scan = Cloud(frames.points[0], frames.planar, 2.0 * fine) if fuse else None
        for i in progress(range(1, n), "icp warm start", unit="frame", enabled=self.progress):
            delta = increments[i - 1] if increments is not None else velocity
            predicted = poses[i - 1] @ delta
            source = Cloud(frames.points[i], frames.planar, 2.0 * fine)
            if fuse:
                poses[i] = self._fused_step(i, source, target, poses[i - 1], predicted, distances)
            else:
                poses[i] = self._plain_step(i, source, target, poses[i - 1], predicted, distances, method,
                                            frames.planar, increments is None)
            if fuse:
                self._previous_scan = source
            velocity = se3.relative(poses[i - 1], poses[i])
            moved = se3.relative(last_key, poses[i])
            if np.linalg.norm(moved[:3, 3]) > kf_dist or rotation_angle(moved[:3, :3]) > kf_angle:
                keyframes.append(se3.transform_points(poses[i], source.points))
                last_key = poses[i]
                target = self._map(keyframes, frames.planar, voxel, fine)
        if fuse and self.windows == "auto":
            poses = self._check_windows(frames, poses, given.poses, fine)
        self.report = self._fusion_report(poses) if fuse else {"fused": False, "rejected": len(self.rejected)}
        return poses

    def _match_weights(self, frames: Frames, given: Trajectory, fine: float) -> MatchWeights:
        """The weights the scan matches are taken with; ``_measured`` keeps what the cycles found (None: not
        measured) and ``_weighed`` how the matches were taken ("whole" or "cycles"), which the report gives as
        ``match_weights.weights`` (measured) and ``match_weights.weighed``."""
        if self.weigh not in ("auto", "cycles", "whole"):
            raise InputError(None, f"icp warm start: unknown weigh {self.weigh!r} (auto, whole, cycles)")
        self._measured: MatchWeights | None = None
        self._weighed = "whole"
        if self.weigh == "whole":
            return MatchWeights.whole()
        odometry = np.array([project_planar(T) for T in given.poses])
        self._measured = match_weights(frames.points, odometry, fine, self.iterations)
        if self._measured.triples < MIN_TRIPLES or (self.weigh == "auto" and self._measured.more_precise != "odometry"):
            return MatchWeights.whole(self._measured.triples)
        self._weighed = "cycles"
        return self._measured

    def _check_windows(self, frames: Frames, poses: np.ndarray, odometry: np.ndarray, fine: float) -> np.ndarray:
        """:func:`check_windows` over windows one median scan range long, the odometry's per-step noise from the
        per-step differences of the scan matches; the poses with the odometry's increments where it won."""
        dt, dr = self._cols["dt"], self._cols["dyaw"]
        ok = np.isfinite(dt)
        if ok.sum() < 20:
            return poses
        share_t, share_r = self._odometry_share()
        noise = OdometryNoise(max(1.4826 * float(np.median(dt[ok])) * share_t, 1e-3 * fine),
                              max(1.4826 * float(np.median(dr[ok])) * share_r, 1e-3 * fine / self._reach))
        odometry = np.array([project_planar(T) for T in odometry])
        self.verdicts = check_windows(frames.points, poses, odometry, noise, self._reach, fine,
                                      unjudged=self._weights.more_precise)
        return apply_verdicts(poses, odometry, self.verdicts)

    def _plain_step(self, i, source, target, previous, predicted, distances, method, planar, velocity) -> np.ndarray:
        """Pose of frame i: the ICP result from the prediction, or the prediction when the fitness is too low."""
        match = register(source, target, predicted, distances, method, self.iterations, self.prior_weight)
        if velocity and match.fitness < self.retry_fitness:
            # constant velocity may overshoot a stop: also try standing still, keep it if clearly better
            still = register(source, target, previous, distances, method, self.iterations, self.prior_weight)
            if still.fitness > match.fitness + 0.1:
                match = still
        if match.fitness >= self.min_fitness and np.isfinite(match.T).all():
            return project_planar(match.T) if planar else orthonormal(match.T)
        self.rejected.append(i)
        return predicted

    # ------------------------------------------------------------------ fusion with odometry (planar)
    SOURCES: ClassVar[tuple[str, ...]] = ("scan", "scan across, odometry along", "scan, odometry yaw", "odometry")

    def _fusing(self, frames: Frames, increments: np.ndarray | None, method: str) -> bool:
        if self.fuse not in ("auto", "off"):
            raise InputError(None, f"icp warm start: unknown fuse {self.fuse!r} (auto, off)")
        if self.windows not in ("auto", "off"):
            raise InputError(None, f"icp warm start: unknown windows {self.windows!r} (auto, off)")
        if not 0 < self.min_constraint < 0.5 or not self.gate > 0:
            raise InputError(None, "icp warm start: min_constraint must lie in (0, 0.5) and gate be positive")
        return self.fuse == "auto" and increments is not None and frames.planar and method != "point-to-point"

    def _start_fusion(self, n: int, fine: float, range_median: float) -> None:
        self._fine, self._reach = fine, max(range_median, fine)
        self._source = np.zeros(n, dtype=np.int8)  # index into SOURCES; frame 0 is the given start
        self._reason: dict[int, tuple[StepReason, str]] = {}
        self._cols = {k: np.full(n, np.nan) for k in ("fitness", "constraint", "yaw_constraint", "dt", "dyaw")}
        self._recent_t: deque[float] = deque(maxlen=200)  # scan-vs-odometry differences of accepted steps
        self._recent_r: deque[float] = deque(maxlen=200)

    def _gates(self) -> tuple[float, float]:
        """Translation (m) and yaw (rad) gates: ``gate`` robust sigmas of the recent differences between the
        accepted scan matches and the odometry, at least a fine distance (and its angle at the median range)."""
        floor_t, floor_r = self._fine, self._fine / self._reach
        if len(self._recent_t) < 20:
            return 2.0 * floor_t, 2.0 * floor_r
        st = 1.4826 * float(np.median(self._recent_t))
        sr = 1.4826 * float(np.median(self._recent_r))
        return max(floor_t, self.gate * st), max(floor_r, self.gate * sr)

    def _odometry_sigmas(self) -> tuple[float, float]:
        """The odometry's own per-step noise (translation m, yaw rad): the robust spread of the recent differences
        between accepted scan matches and the odometry, times the square root of the match weights (the share of
        those differences that is the odometry's; :mod:`dm2_backend.algorithms.match_noise`), at least a tenth of a
        fine distance (and its angle at the median range)."""
        floor = 0.1 * self._fine
        if len(self._recent_t) >= 20:
            st = 1.4826 * float(np.median(self._recent_t))
            sr = 1.4826 * float(np.median(self._recent_r))
        else:
            st, sr = self._fine, self._fine / self._reach
        share_t, share_r = self._odometry_share()
        return max(st * share_t, floor), max(sr * share_r, floor / self._reach)

    def _odometry_share(self) -> tuple[float, float]:
        """The odometry's share of the spread of scan-vs-odometry differences (which hold the matches' noise too),
        on translation (the larger of along and across) and on yaw: the square roots of the match weights."""
        w = np.sqrt(self._weights.weights)
        return float(max(w[0], w[1])), float(w[2])

    def _odometry_weights(self, rmse: float) -> tuple[float, float]:
        """The odometry's information on one translation direction and on yaw, in the units of the point-to-line
        cost (residual variance / odometry variance, :meth:`_odometry_sigmas`); the residual sigma is the match's
        rmse (at least a tenth of a fine distance)."""
        st, sr = self._odometry_sigmas()
        var = max(rmse, 0.1 * self._fine) ** 2 if np.isfinite(rmse) else self._fine**2
        return var / st**2, var / sr**2

    def _fused_step(self, i: int, source: Cloud, target: Cloud, previous: np.ndarray, predicted: np.ndarray,
                    distances) -> np.ndarray:
        """Pose of frame i: the scan match, the scan match with its degenerate directions from the odometry,
        or the odometry increment, with the source and reason recorded."""
        fine = distances[-1]
        xy = source.xy
        match = register(source, target, predicted, distances, "point-to-plane", self.iterations, self.prior_weight)
        T = project_planar(match.T) if np.isfinite(match.T).all() else predicted
        info = information_2d(xy, target, T, fine)
        cols = self._cols
        if not np.isfinite(match.T).all() or info["fitness"] < self.min_fitness:
            cols["fitness"][i] = info["fitness"]
            return self._use_odometry(i, predicted, StepReason.OVERLAP,
                                      f"overlap {info['fitness']:.2f} < {self.min_fitness:.2f}")
        # slide the match one fine distance along the weakest translation direction (and turn it so that points
        # at the median range move as far): the share of the scan that leaves the map says whether the scan
        # holds that direction, measured on the points themselves rather than on their (noisy) normals
        along = slide_loss(xy, target, T, np.array([*(fine * info["weak_axis"]), 0.0]), fine)
        turn = slide_loss(xy, target, T, np.array([0.0, 0.0, fine / self._reach]), fine)
        for key, value in (("fitness", info["fitness"]), ("constraint", along), ("yaw_constraint", turn)):
            cols[key][i] = value
        # both tests must agree: noisy normals make the information pessimistic near walls seen at a graze, and
        # the slide test alone is pessimistic where a few points (a door frame) hold the scan firmly
        weak_t = along < self.min_constraint and info["weak"] < self.min_constraint
        weak_r = turn < self.min_constraint and info["yaw"] < (self.min_constraint * self._reach) ** 2
        if weak_t and weak_r:
            return self._use_odometry(i, predicted, StepReason.DEGENERATE, "degenerate in translation and yaw")
        source_kind = 0
        if weak_t or weak_r:
            # hold the degenerate direction at the odometry's prediction, match the others
            hold = np.zeros((3, 3))
            w_t, w_r = self._odometry_weights(info["rmse"])
            if weak_t:
                v = info["weak_axis"]
                hold[:2, :2] = w_t * np.outer(v, v)
                source_kind = 1
            if weak_r:
                hold[2, 2] = w_r
                source_kind = 2 if not weak_t else source_kind
            match = register(source, target, predicted, distances, "point-to-plane", self.iterations, 0.0,
                             prior_info=hold)
            if not np.isfinite(match.T).all():
                return self._use_odometry(i, predicted, StepReason.DIVERGED, "ICP diverged")
            T = project_planar(match.T)
            info = information_2d(xy, target, T, fine)
            if info["fitness"] < self.min_fitness:
                return self._use_odometry(i, predicted, StepReason.OVERLAP,
                                          f"overlap {info['fitness']:.2f} < {self.min_fitness:.2f}")
        # agreement with the odometry increment
        d = se3.to_xy_yaw(se3.relative(predicted, T))
        dt, dr = float(np.hypot(d[0], d[1])), abs(float(d[2]))
        cols["dt"][i], cols["dyaw"][i] = dt, dr
        gate_t, gate_r = self._gates()
        if dt > gate_t or dr > gate_r:
            # judged on the previous scan alone: the local map holds the last steps, which may have bent it
            before = self._previous_scan
            at_odometry = information_2d(xy, before, se3.relative(previous, predicted), fine)["fitness"]
            at_match = information_2d(xy, before, se3.relative(previous, T), fine)["fitness"]
            if at_match < at_odometry + self.better_fitness:
                return self._use_odometry(
                    i, predicted, StepReason.DISAGREES,
                    f"disagrees with the odometry ({dt:.3f} m, {np.degrees(dr):.2f} deg; gate {gate_t:.3f} m, "
                    f"{np.degrees(gate_r):.2f} deg) without fitting the previous scan clearly better (overlap "
                    f"{at_match:.2f} vs {at_odometry:.2f})")
            # a wheel slips or a gyro jumps: the odometry can report motion the robot did not make, but not carry it
            # farther than its wheels turned (that is a scan match sliding along a hall)
            travel = float(np.linalg.norm(se3.relative(previous, T)[:2, 3]))
            wheels = float(np.linalg.norm(se3.relative(previous, predicted)[:2, 3]))
            allowance = self.gate * self._odometry_sigmas()[0]
            if travel > wheels + allowance:
                return self._use_odometry(
                    i, predicted, StepReason.FARTHER,
                    f"the scan match moves {travel:.3f} m where the odometry moved {wheels:.3f} m (allowance "
                    f"{allowance:.3f} m): a match sliding, not a wheel slipping")
            self._reason[i] = (StepReason.GLITCH, f"odometry glitch: {dt:.3f} m, {np.degrees(dr):.2f} deg off, the "
                               f"scan fits the previous one better (overlap {at_match:.2f} vs {at_odometry:.2f})")
        else:
            self._recent_t.append(dt)
            self._recent_r.append(dr)
        if source_kind == 1:
            self._reason.setdefault(i, (StepReason.TRANSLATION,
                                        f"translation degenerate (slide cost {cols['constraint'][i]:.3f} < "
                                        f"{self.min_constraint}): along {np.round(info['weak_axis'], 2).tolist()} "
                                        "from the odometry"))
        elif source_kind == 2:
            self._reason.setdefault(i, (StepReason.YAW, f"yaw degenerate (turn cost {cols['yaw_constraint'][i]:.3f}"
                                                         f" < {self.min_constraint}): yaw from the odometry"))
        self._source[i] = source_kind
        glitch = i in self._reason and self._reason[i][0] is StepReason.GLITCH
        return T if glitch else self._weights.blend(predicted, T)

    def _use_odometry(self, i: int, predicted: np.ndarray, code: StepReason, message: str) -> np.ndarray:
        self._source[i] = 3
        self._reason[i] = (code, message)
        self.rejected.append(i)
        return predicted

    def _fusion_report(self, poses: np.ndarray) -> dict:
        src = self._source[1:]
        counts = {name: int((src == k).sum()) for k, name in enumerate(self.SOURCES)}
        kinds: dict[str, int] = {}
        for code, _ in self._reason.values():
            kinds[code.value] = kinds.get(code.value, 0) + 1
        r = lambda a: [None if not np.isfinite(v) else round(float(v), 4) for v in a]  # noqa: E731
        reasons = dict(sorted(kinds.items(), key=lambda kv: -kv[1]))
        summary = (f"icp warm start: {counts['scan']} of {len(src)} steps from the scan match, "
                   + ", ".join(f"{v} {k}" for k, v in list(counts.items())[1:]) + "; "
                   + (", ".join(f"{k}: {v}" for k, v in reasons.items()) or "no fallback"))
        w = self._measured
        if w is not None and w.triples >= MIN_TRIPLES:
            measured = ", ".join(f"{x:.2f} {a}" for x, a in zip(w.weights, AXES))
            summary += (f"; scan matches weighed {measured} against the odometry ({w.triples} match cycles)"
                        if self._weighed == "cycles" else
                        f"; scan matches taken whole (their {w.triples} match cycles weigh them {measured}: the "
                        "odometry is not the more precise source on every axis)")
        fallback = [v for v in self.verdicts if v.source == "odometry"]
        if self.verdicts:
            summary += (f"; windows of {self._reach:.1f} m: {len(fallback)} of {len(self.verdicts)} from the odometry"
                        + (f" (scan matching drifted: {', '.join(f'{v.start}-{v.end}' for v in fallback[:10])}"
                           + (", ..." if len(fallback) > 10 else "") + ")" if fallback else ""))
        return {
            "fused": True,
            "summary": summary,  # printed by the preparation, whether computed or read from the cache
            "steps": int(len(src)),
            "sources": counts,
            "reasons": reasons,
            "windows": [asdict(v) for v in self.verdicts],
            "match_weights": (self._measured or self._weights).as_dict() | {"weighed": self._weighed},
            "settings": {"min_fitness": self.min_fitness, "min_constraint": self.min_constraint,
                         "gate": self.gate, "better_fitness": self.better_fitness, "windows": self.windows,
                         "weigh": self.weigh, "unjudged_windows": self._weights.more_precise,
                         "fine_distance_m": round(self._fine, 4), "range_median_m": round(self._reach, 4)},
            "per_step": {
                "source": [self.SOURCES[k] for k in self._source.tolist()],
                "reason": [self._reason[i][1] if i in self._reason else "" for i in range(len(self._source))],
                **{k: r(v) for k, v in self._cols.items()},
            },
        }

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
