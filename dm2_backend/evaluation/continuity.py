"""Whether a trajectory keeps the sequence's steps, judged without ground truth: a step that the front end's odometry
and the scans' own registration of the two frames both contradict is a cut.

Each step ``i -> i+1`` of a candidate is compared with the odometry step and, where valid, the registration of
the pair: its offset from each (translation, rotation angle). A source explains a step whose offset is within
:data:`RATIO` times that source's median offset over the sequence (a robust scale: a cut or two do not move it)
or within how far a scan-matching step slides (``slip_m``, the registration's coarse correspondence distance;
``slip_m`` over the scans' median range in rotation). A step is cut when neither source explains it. The
registrations judge only where there are :data:`MIN_STEPS` of them (else the odometry judges alone); a sequence
of fewer steps is not judged at all.

Why: a pose graph whose robust kernel meets a clique of wrong registrations can cut the odometry chain. Where
many loop registrations slide along walls that look alike, a robust solution can give up one odometry edge and snap
each stretch onto the wrong alignments; its map can be sharper by entropy and its frames agree with the others'
planes, each stretch being a consistent picture of a place whose views look alike; its steps are not. Why the
slide allowance: a scan-matching front end slides now and then where the scans leave a direction free, the
registration of the same pair slides the same way, and a solution that repairs such a step is not a cut
(docs/decisions/0002-start-judged-by-planes.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.kernel.geometry import se3

#: a step further from a source than this many times the sequence's median offset from it is not explained by
#: it. The offset of a step with normal noise is a chi variable of 3 degrees of freedom, whose median is 1.54
#: sigma: ten medians are 15 sigma, far beyond the largest of a 20,000-frame sequence (4.8 sigma typically, 5.7
#: once in a hundred), which leaves room for the heavier tails of a real front end
RATIO = 10.0
#: the fewest steps (or registrations) a robust scale is taken over; a shorter sequence is not judged, fewer
#: registrations leave the odometry to judge alone
MIN_STEPS = 20


@dataclass
class Cuts:
    """The cut steps (``steps[k]``: frame ``steps[k]`` to the next) and how far each is from the odometry."""

    steps: np.ndarray
    offset_m: np.ndarray
    offset_deg: np.ndarray
    judged: bool = True  # False: too few steps to judge (nothing is cut)

    def __bool__(self) -> bool:
        return len(self.steps) > 0

    def describe(self, most: int = 3) -> str:
        """``step 235 (1.36 m, 50.1 deg from the odometry)`` for the largest ``most`` cuts, ranked by
        max(translation / largest translation, rotation / largest rotation)."""
        size = np.maximum(self.offset_m / max(self.offset_m.max(initial=0.0), 1e-12),
                          self.offset_deg / max(self.offset_deg.max(initial=0.0), 1e-12))
        order = np.argsort(-size, kind="stable")[:most]
        text = ", ".join(f"step {self.steps[k]} ({self.offset_m[k]:.3g} m, {self.offset_deg[k]:.3g} deg from the "
                         "odometry)" for k in order)
        more = len(self.steps) - len(order)
        return text + (f" and {more} more" if more > 0 else "")

    def summary(self) -> dict:
        return {"judged": self.judged, "steps": self.steps.tolist(), "offset_m": self.offset_m.tolist(),
                "offset_deg": self.offset_deg.tolist()}


def _offsets(measured: np.ndarray, poses: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (rad) of ``inv(measured[k]) inv(P_i) P_{i+1}`` for each ``i = steps[k]``."""
    d = se3.relative(measured, se3.relative(poses[steps], poses[steps + 1]))
    return np.linalg.norm(d[:, :3, 3], axis=1), se3.rotation_angle(d[:, :3, :3])


def _unexplained(measured: np.ndarray, poses: np.ndarray, steps: np.ndarray, slip_t: float, slip_r: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of ``steps`` the ``measured`` relative poses do not explain, and the offsets from them."""
    t, r = _offsets(measured, poses, steps)
    return (t > max(RATIO * np.median(t), slip_t)) | (r > max(RATIO * np.median(r), slip_r)), t, r


def cuts(poses: np.ndarray, odometry: np.ndarray, registered: dict[int, np.ndarray], slip_m: float,
         range_m: float) -> Cuts:
    """The steps of ``poses`` that neither the front end's ``odometry`` (its poses: their steps are the
    measurements) nor ``registered`` (step i -> the registered pose of frame i+1 in frame i, where valid)
    explain; ``slip_m`` and ``slip_m / range_m`` (rad; ``range_m`` the scans' median range) the smallest offsets
    called a cut. Fewer than :data:`MIN_STEPS` steps: nothing is judged; fewer valid registrations: the odometry
    judges alone."""
    n = len(poses) - 1
    empty = np.zeros(0)
    if n < MIN_STEPS:
        return Cuts(np.zeros(0, int), empty, empty, judged=False)
    slip_r = slip_m / max(range_m, 1e-9)
    steps = np.arange(n)
    odometry = np.asarray(odometry, dtype=np.float64)
    cut, t, r = _unexplained(se3.relative(odometry[:-1], odometry[1:]), poses, steps, slip_m, slip_r)
    with_reg = np.array(sorted(i for i in registered if 0 <= i < n), dtype=int)
    if len(with_reg) >= MIN_STEPS:
        measured = np.stack([registered[int(i)] for i in with_reg])
        off_reg, _, _ = _unexplained(measured, poses, with_reg, slip_m, slip_r)
        cut[with_reg[~off_reg]] = False
    found = np.flatnonzero(cut)
    return Cuts(found, t[found], np.degrees(r[found]))
