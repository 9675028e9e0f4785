"""Scan matching against wheel odometry at the scale where drift shows: windows of path, not steps.

A per-step test cannot see a bias of a few centimetres a step (max-range codes pulling every match towards
standing still, a wrong lever arm): it hides in the steps' noise and sums to metres. Over a window of path (one
median scan range long: the scans at its two ends still see the same walls) the warm start's relative pose and
the odometry's are compared. Where they disagree by more than the odometry's own noise explains, the window's
end scans are the judge, where both ends see: the candidate (scan-matched or odometry relative pose) that lays the
last scans of the window onto its first ones clearly better wins; where they cannot tell the two apart (a hall
seen along its axis), the odometry does (the scans hold nothing there that the matches could have used), unless
they lean towards the scan match (no evidence that scan matching drifted: the odometry can be the one that turned);
where they see nothing in common (a turn on the spot), the source named ``unjudged`` (the scans by default; the
fused warm start passes the one its match cycles found the more precise: :mod:`dm2_backend.algorithms.match_noise`).
The odometry's increments replace the window's where it wins. Every window gets a :class:`WindowVerdict`
(docs/decisions/0010-fused-warm-start-windows.md, docs/decisions/0015-scan-weights-from-match-cycles.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.gates import depth_image
from dm2_backend.kernel.geometry import se3

#: a window's two candidates differ "clearly" when their mean per-point costs differ by this many standard errors of
#: the paired differences
CLEAR = 3.0
#: disagreement above this many standard deviations of the odometry's window error is systematic
SYSTEMATIC = 3.0


@dataclass(frozen=True)
class WindowVerdict:
    """Which source a window of the warm start took, and why."""

    start: int
    end: int
    #: path length of the window along the odometry (m)
    length_m: float
    #: the warm start's relative pose over the window against the odometry's: translation along and across the
    #: window's chord (m) and yaw (deg)
    along_m: float
    across_m: float
    yaw_deg: float
    #: what the odometry's noise explains over the window (m, m, deg): ``SYSTEMATIC`` standard deviations of its
    #: random walk (an upper bound: the per-step differences it is estimated from hold the scan matches' noise too)
    explained_along_m: float
    explained_across_m: float
    explained_deg: float
    #: (judged windows) share of the compared end-scan points within ``fine`` of the other end's at each candidate,
    #: and the difference of mean per-point cost that is "clear"; None where not judged
    overlap_scan: float | None
    overlap_odometry: float | None
    margin: float | None
    #: "scan" or "odometry"
    source: str
    reason: str


@dataclass(frozen=True)
class OdometryNoise:
    """The odometry's per-step noise, estimated from the log: robust spread of the per-step differences between
    accepted scan matches and the odometry (translation m, yaw rad)."""

    trans: float
    yaw: float


def window_bounds(odometry: np.ndarray, length: float, min_steps: int) -> list[tuple[int, int]]:
    """Consecutive windows [a, b] of at least ``length`` metres of odometry path and ``min_steps`` steps; the last
    one takes the remainder."""
    step = np.linalg.norm(np.diff(odometry[:, :2, 3], axis=0), axis=1)
    out, a, run = [], 0, 0.0
    for i, d in enumerate(step, start=1):
        run += d
        if run >= length and i - a >= min_steps:
            out.append((a, i))
            a, run = i, 0.0
    if a < len(odometry) - 1:
        if out and len(odometry) - 1 - a < min_steps:
            out[-1] = (out[-1][0], len(odometry) - 1)
        else:
            out.append((a, len(odometry) - 1))
    return out


def _end_cloud(points: list[np.ndarray], poses: np.ndarray, idx: range, ref: int, radius: float,
               within: float) -> Cloud:
    """The scans ``idx`` merged in the frame of scan ``ref`` at ``poses`` (planar), their points ``within`` metres of
    the sensor only: the surfaces both ends of a window see (not max-range codes or stray long returns)."""
    near = [p[np.linalg.norm(p[:, :2], axis=1) <= within].astype(np.float64) for p in points[idx.start:idx.stop]]
    pts = [se3.transform_points(se3.relative(poses[ref], poses[k]), q) for k, q in zip(idx, near, strict=True)]
    return Cloud(np.concatenate(pts), True, radius)


def check_windows(points: list[np.ndarray], warm: np.ndarray, odometry: np.ndarray, noise: OdometryNoise,
                  reach: float, fine: float, end_scans: int = 3, unjudged: str = "scan") -> list[WindowVerdict]:
    """A :class:`WindowVerdict` per window of ``reach`` metres (the median scan range; at least ``end_scans`` x 3
    steps): the warm start ``warm`` against the ``odometry`` (both (N, 4, 4) planar). A disagreement within
    ``SYSTEMATIC`` standard deviations of the odometry's random walk (``noise`` per step; along, across and in yaw)
    keeps the scans. Beyond it, the window's last ``end_scans`` scans are laid onto its first ones (and back) at
    either candidate, points within ``2 reach`` of their sensor and where the other end sees only; the per-point
    cost (distance in ``fine`` units, squared, at most 1) decides when the paired difference exceeds ``CLEAR``
    standard errors, else the odometry, unless the scan match lays the end scans closer (then the scans). Where the
    end scans see nothing in common, ``unjudged`` decides: the source the match cycles found the more precise
    (:mod:`dm2_backend.algorithms.match_noise`)."""
    verdicts = []
    for a, b in window_bounds(odometry, reach, 3 * end_scans):
        n = b - a
        rel_w, rel_o = se3.relative(warm[a], warm[b]), se3.relative(odometry[a], odometry[b])
        d = se3.to_xy_yaw(se3.relative(rel_o, rel_w))  # in the frame of the window's end
        chord = rel_o[:2, :2].T @ rel_o[:2, 3]
        u = chord / max(float(np.linalg.norm(chord)), 1e-9)
        along, across = float(d[:2] @ u), float(u[0] * d[1] - u[1] * d[0])
        dr = abs(float(d[2]))
        path = float(np.linalg.norm(np.diff(odometry[a:b + 1, :2, 3], axis=0), axis=1).sum())
        # a random walk of n steps; a yaw error turns the window's chord as well
        walk, sd_r = noise.trans * np.sqrt(n), noise.yaw * np.sqrt(n)
        explained = SYSTEMATIC * np.array([walk, np.hypot(walk, sd_r * path / 2.0), sd_r])
        systematic = abs(along) > explained[0] or abs(across) > explained[1] or dr > explained[2]
        common = dict(start=a, end=b, length_m=round(path, 3), along_m=round(along, 4), across_m=round(across, 4),
                      yaw_deg=round(float(np.degrees(d[2])), 3), explained_along_m=round(float(explained[0]), 4),
                      explained_across_m=round(float(explained[1]), 4),
                      explained_deg=round(float(np.degrees(explained[2])), 3))
        what = (f"{along:+.3f} m along, {across:+.3f} m across, {np.degrees(d[2]):+.2f} deg from the odometry over "
                f"{path:.1f} m (its noise explains {explained[0]:.3f}, {explained[1]:.3f} m, "
                f"{np.degrees(explained[2]):.2f} deg)")
        if not systematic:
            verdicts.append(WindowVerdict(**common, overlap_scan=None, overlap_odometry=None, margin=None,
                                          source="scan", reason=f"within the odometry's noise: {what}"))
            continue
        k = min(end_scans, max(1, n // 3))
        head = _end_cloud(points, warm, range(a, a + k), a, 2.0 * fine, 2.0 * reach)
        tail = _end_cloud(points, warm, range(b - k + 1, b + 1), b, 2.0 * fine, 2.0 * reach)
        pairs = [(tail, head, rel_w, rel_o), (head, tail, se3.inverse(rel_w), se3.inverse(rel_o))]
        costs = [np.concatenate(c) for c in zip(*[_compared(m, f, A, B, fine) for m, f, A, B in pairs], strict=True)]
        if len(costs[0]) < 10:
            verdicts.append(WindowVerdict(**common, overlap_scan=None, overlap_odometry=None, margin=None,
                                          source=unjudged, reason=f"not judged: {what}, but the end scans see nothing "
                                          f"in common (e.g. a turn on the spot): the more precise source, {unjudged}"))
            continue
        fits = [float(np.mean(c < 1.0)) for c in costs]
        # paired over the points: how much closer to the other end's scans each point lies at the odometry's pose
        gain = costs[0] - costs[1]
        margin = CLEAR * float(np.std(gain)) / np.sqrt(len(gain))
        better = float(np.mean(gain))
        scores = (f"end scans overlap {fits[0]:.3f} at the scan match, {fits[1]:.3f} at the odometry, mean cost "
                  f"{np.mean(costs[0]):.3f} vs {np.mean(costs[1]):.3f}")
        if -better > margin:
            source, reason = "scan", f"the odometry drifted: {what}; {scores} (clearly: > {margin:.3f})"
        elif better > margin:
            source, reason = "odometry", f"scan matching drifted: {what}; {scores} (clearly: > {margin:.3f})"
        elif better < 0.0:
            source, reason = "scan", (f"scan matching unconfirmed but favoured: {what}; the end scans lie closer at "
                                      f"the scan match, not clearly; {scores} (within {margin:.3f})")
        else:
            source, reason = "odometry", (f"scan matching unconfirmed: {what}, more than the odometry's noise "
                                          f"explains, and the scans cannot tell; {scores} (within {margin:.3f})")
        verdicts.append(WindowVerdict(**common, overlap_scan=round(fits[0], 4), overlap_odometry=round(fits[1], 4),
                                      margin=round(margin, 4), source=source, reason=reason))
    return verdicts


def _compared(moving: Cloud, fixed: Cloud, A: np.ndarray, B: np.ndarray, distance: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_costs` of the ``moving`` points at ``A`` and at ``B`` that the ``fixed`` scans would see at both: in a
    bearing where they have returns, not behind those by more than ``distance`` (comparing only there keeps the
    edges of what each end saw from favouring the candidate that lays the clouds closer together)."""
    seen = _observable(moving, fixed, A, distance) & _observable(moving, fixed, B, distance)
    return _costs(moving, fixed, A, distance)[seen], _costs(moving, fixed, B, distance)[seen]


def _observable(moving: Cloud, fixed: Cloud, T: np.ndarray, distance: float, bins: int = 360) -> np.ndarray:
    p = se3.transform_points(T, moving.points)
    image = depth_image(fixed, bins)
    far = image.depth[0, ((np.arctan2(p[:, 1], p[:, 0]) + np.pi) / (2 * np.pi) * bins).astype(int) % bins]
    return np.isfinite(far) & (np.linalg.norm(p[:, :2], axis=1) <= far + distance)


def _costs(moving: Cloud, fixed: Cloud, T: np.ndarray, distance: float) -> np.ndarray:
    """Per point of ``moving`` at ``T``: the squared distance to ``fixed`` in units of ``distance``, truncated at 1."""
    c, s = T[0, 0], T[1, 0]
    p = moving.xy @ np.array([[c, s], [-s, c]]) + T[:2, 3]
    d, _ = fixed.tree.query(p, distance_upper_bound=distance)
    return np.minimum(d / distance, 1.0) ** 2


def apply_verdicts(warm: np.ndarray, odometry: np.ndarray, verdicts: list[WindowVerdict]) -> np.ndarray:
    """The warm start with the odometry's increments over every window whose verdict is "odometry" (the poses before
    the first such window unchanged)."""
    fallback = [v for v in verdicts if v.source == "odometry"]
    if not fallback:
        return warm
    inc = se3.relative(warm[:-1], warm[1:])
    odo = se3.relative(odometry[:-1], odometry[1:])
    for v in fallback:
        inc[v.start:v.end] = odo[v.start:v.end]
    out = warm.copy()
    for i in range(fallback[0].start + 1, len(warm)):
        out[i] = out[i - 1] @ inc[i - 1]
    return out
