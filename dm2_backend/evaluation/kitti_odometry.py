"""The KITTI odometry benchmark's metric, as its devkit (``devkit_odometry``, ``evaluate_odometry.cpp``) computes it.

On associated poses (N,4,4), ground truth and estimate paired one to one, as they are (no alignment: the metric
only looks at relative poses, so each trajectory's own origin does not matter):

1. ``trajectoryDistances``: the ground truth's cumulative path length ``dist`` (0 at the first pose);
2. segments: first frames every ``STEP_FRAMES`` = 10 frames (0, 10, 20, ...), lengths ``LENGTHS_M`` =
   100, 200, ..., 800 m; ``lastFrameFromSegmentLength``: the first frame whose distance exceeds (strictly)
   ``dist[first] + length``; no such frame, no segment;
3. for each segment: ``delta_gt = inv(gt[first]) @ gt[last]``, ``delta_est = inv(est[first]) @ est[last]``,
   ``E = inv(delta_est) @ delta_gt``; ``rotationError`` = ``acos(clip(0.5 * (E00 + E11 + E22 - 1), -1, 1))``,
   ``translationError`` = the norm of E's translation; both divided by the segment's length;
4. the figures: the mean over every segment of the sequence (the devkit's ``stats.txt``: a fraction and rad/m),
   reported as papers and KISS-ICP do: translation in % (x 100), rotation in deg/100 m (x 180/pi x 100).

The devkit reads camera-frame (cam0) poses; ``frame`` takes poses held in another frame back to it (KITTI's
``Tr``: LiDAR-frame poses ``T`` are evaluated as ``Tr @ T @ inv(Tr)``). It computes in single precision where
this module uses double; its ``Matrix::inv`` is a general inverse where this module uses the rigid one (the same
for rotation matrices). A ground-truth path not longer than 100 m has no segment: the metric does not apply.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry import se3

#: the devkit's segment lengths (m) and the step between first frames
LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
STEP_FRAMES = 10
DEFINITION = ("KITTI odometry devkit (evaluate_odometry.cpp): segments of 100-800 m of ground-truth path starting "
              "every 10th frame, no alignment; mean over segments of the relative pose error per metre; "
              "t_err in %, r_err in deg/100 m")


@dataclass(frozen=True)
class KittiLength:
    """The mean errors of the segments of one length."""

    length_m: float
    segments: int
    t_err_percent: float
    r_err_deg_per_100m: float


@dataclass(frozen=True, eq=False)
class KittiOdometryError:
    """The KITTI odometry metric of one estimate. ``applicable`` is False (no segment; the figures None) when
    the ground-truth path is not longer than the shortest segment (100 m). The per-segment arrays are in the
    devkit's order (first frame, then length) and in the reported units."""

    path_m: float  # the ground truth's path length
    poses: int
    t_err_percent: float | None
    r_err_deg_per_100m: float | None
    per_length: tuple[KittiLength, ...]
    segment_first: np.ndarray  # (S,) first frame of each segment
    segment_last: np.ndarray  # (S,) last frame
    segment_length_m: np.ndarray  # (S,) its nominal length (100 ... 800)
    segment_t_err_percent: np.ndarray  # (S,) translation error / length x 100
    segment_r_err_deg_per_100m: np.ndarray  # (S,) rotation error / length, deg/100 m

    @property
    def segments(self) -> int:
        return len(self.segment_first)

    @property
    def applicable(self) -> bool:
        return self.segments > 0

    def line(self) -> str:
        """One line for the terminal: the two figures, or why there are none."""
        if not self.applicable:
            return f"KITTI odometry metric: path {self.path_m:.1f} m is shorter than {LENGTHS_M[0]:.0f} m"
        return result_line(self.t_err_percent, self.r_err_deg_per_100m, self.segments)

    def as_dict(self) -> dict:
        """The JSON entry (``kitti_odometry`` of ``dm2 eval --json`` and ``report.json``)."""
        return {
            "applicable": self.applicable, "t_err_percent": self.t_err_percent,
            "r_err_deg_per_100m": self.r_err_deg_per_100m, "segments": self.segments, "path_m": self.path_m,
            "poses": self.poses, "lengths_m": list(LENGTHS_M), "step_frames": STEP_FRAMES,
            "per_length": [{"length_m": k.length_m, "segments": k.segments, "t_err_percent": k.t_err_percent,
                            "r_err_deg_per_100m": k.r_err_deg_per_100m} for k in self.per_length],
            "definition": DEFINITION,
        }

    def metrics(self) -> dict[str, float]:
        """The flat metrics of a run report (none when not applicable)."""
        if not self.applicable:
            return {}
        return {"kitti_t_err_percent": float(self.t_err_percent),
                "kitti_r_err_deg_per_100m": float(self.r_err_deg_per_100m)}


def result_line(t_err_percent: float, r_err_deg_per_100m: float, segments: int) -> str:
    """``KITTI odometry: t_err 1.23 % r_err 0.456 deg/100 m over 312 segments``."""
    return (f"KITTI odometry: t_err {figure(t_err_percent)} % r_err {figure(r_err_deg_per_100m)} deg/100 m "
            f"over {segments} segments")


def figure(value: float) -> str:
    """Three significant digits without an exponent: 1.23, 0.456, 0.00412, 123."""
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    return f"{value:.{max(0, 2 - math.floor(math.log10(abs(value))))}f}"


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """The devkit's ``trajectoryDistances``: cumulative path length at each pose (0 at the first)."""
    steps = np.linalg.norm(np.diff(np.asarray(poses, dtype=np.float64)[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_error(E: np.ndarray) -> np.ndarray:
    """The devkit's ``rotationError``: the angle (rad) of the rotation part, from its trace, clipped."""
    trace = E[..., 0, 0] + E[..., 1, 1] + E[..., 2, 2]
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


def kitti_odometry_error(gt: np.ndarray, est: np.ndarray, frame: np.ndarray | None = None) -> KittiOdometryError:
    """The KITTI odometry metric of ``est`` against ``gt`` (associated poses (N,4,4), the same N); ``frame``:
    evaluate ``frame @ T @ inv(frame)`` instead of the poses ``T`` (see the module's docstring)."""
    gt = np.asarray(gt, dtype=np.float64)
    est = np.asarray(est, dtype=np.float64)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"need two pose arrays (N,4,4) of the same N, got {gt.shape} and {est.shape}")
    if frame is not None:
        frame = np.asarray(frame, dtype=np.float64)
        gt, est = frame @ gt @ se3.inverse(frame), frame @ est @ se3.inverse(frame)
    n = len(gt)
    dist = trajectory_distances(gt) if n else np.zeros(0)
    # every first frame with every length, first frame major as the devkit loops
    first = np.repeat(np.arange(0, n, STEP_FRAMES), len(LENGTHS_M))
    length = np.tile(np.asarray(LENGTHS_M), len(first) // len(LENGTHS_M))
    last = np.searchsorted(dist, dist[first] + length, side="right")  # first index with dist > dist[first] + len
    keep = last < n
    first, last, length = first[keep], last[keep], length[keep]
    delta_gt = se3.relative(gt[first], gt[last])
    delta_est = se3.relative(est[first], est[last])
    E = se3.relative(delta_est, delta_gt)
    t_err = np.linalg.norm(E[:, :3, 3], axis=1) / length * 100.0
    r_err = np.degrees(rotation_error(E)) / length * 100.0
    per_length = tuple(
        KittiLength(L, int(m.sum()), float(t_err[m].mean()), float(r_err[m].mean()))
        for L in LENGTHS_M if (m := length == L).any()
    )
    applicable = len(first) > 0
    return KittiOdometryError(
        path_m=float(dist[-1]) if n else 0.0,
        poses=n,
        t_err_percent=float(t_err.mean()) if applicable else None,
        r_err_deg_per_100m=float(r_err.mean()) if applicable else None,
        per_length=per_length,
        segment_first=first,
        segment_last=last,
        segment_length_m=length,
        segment_t_err_percent=t_err,
        segment_r_err_deg_per_100m=r_err,
    )
