"""Whether each step of a trajectory agrees with the two frames' own data, judged without ground truth.

Each step ``i -> i+1`` is placed at the candidate's relative pose and at each reference step (the valid
registration of the pair, and the front end's odometry step): frame ``i+1``'s points are matched to frame ``i``'s
nearest points within the registration's fine correspondence distance, and the rms of their point-to-plane
(planar scans: point-to-line) residuals is taken. The step's *excess* is how much larger its mean squared residual
is than the best reference's, as a fraction of the latter. A step is *contradicted* when

- its excess lies beyond the sequence's own spread: the median excess plus :data:`RATIO` robust sigmas (1.4826 x
  the median absolute deviation) of the excesses of the steps that differ from their reference (a multi-frame
  solution and the pairwise registrations differ by a little everywhere; a step that breaks stands out by an
  order of magnitude; fewer than :data:`MIN_STEPS` such steps: no spread is taken), and
- the two frames fit every reference better than the candidate beyond chance, point by point
  (:func:`~dm2_backend.algorithms.gates.significantly_worse`): a registration can slide into a spurious minimum
  along a corridor, where the odometry's step, which the candidate keeps, fits the frames as well.

Why: a multi-frame objective can trade a step for a sharper map in the mean. On real depth frames (7-Scenes
RedKitchen 500-999) the dense stage moved a stretch of steps 4-11 cm away from the steps that both the reference
and the frames' registration give, while every whole-map check (map entropy, each frame against the others'
planes) called the result better; the two frames' own residual at those steps was 1.25-2.2x the registration's,
where every other step was within 1.05x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.gates import plane_residual, plane_residuals, significantly_worse
from dm2_backend.geometry import se3

#: a step whose excess lies more than this many robust sigmas above the sequence's median excess stands out
RATIO = 10.0
#: the fewest steps the sequence's spread is taken over; with fewer the point-by-point test judges alone
MIN_STEPS = 20
#: the fewest matched points a residual is taken over (fewer: the step is not judged)
MIN_MATCHED = 10

REGISTRATION = "registration"
ODOMETRY = "odometry"


@dataclass(frozen=True)
class StepCheck:
    """Per step ``steps[k]`` (frame ``steps[k]`` to the next): the candidate's residual, the best reference's
    residual and which reference that was, the excess, and whether the data contradicts the step."""

    steps: np.ndarray
    residual_m: np.ndarray
    reference_residual_m: np.ndarray
    reference: tuple[str, ...]
    reference_step: np.ndarray  # (S, 4, 4) the best reference's relative pose
    excess: np.ndarray
    matched: np.ndarray
    threshold: float  # the excess above which a step is tested point by point (0: every step is)
    contradicted: np.ndarray  # bool
    #: how well all the steps fit their frames: the rms point-to-plane residual (m) over every point of every
    #: second frame, a point without a match within the distance counting as the distance (NaN: none judged)
    fit_m: float = float("nan")

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.contradicted))

    def describe(self, most: int = 5) -> str:
        """``step 282 (residual 2.2x the registration's), ...`` for the ``most`` worst contradicted steps."""
        bad = np.flatnonzero(self.contradicted)
        order = bad[np.argsort(-self.excess[bad], kind="stable")][:most]
        text = ", ".join(f"step {self.steps[k]} (residual {self.residual_m[k] / self.reference_residual_m[k]:.2f}x "
                         f"the {self.reference[k]}'s)" for k in order)
        more = len(bad) - len(order)
        return text + (f" and {more} more" if more > 0 else "")

    def summary(self) -> dict:
        """The per-step record of ``report.json``: every judged step, what it was compared with and the verdict."""
        return {"steps": self.steps.tolist(), "residual_m": self.residual_m.tolist(),
                "reference_residual_m": self.reference_residual_m.tolist(), "reference": list(self.reference),
                "excess": self.excess.tolist(), "threshold": self.threshold, "fit_m": self.fit_m,
                "matched": self.matched.tolist(), "contradicted": np.flatnonzero(self.contradicted).tolist()}


class FramePairs:
    """The frames' points as clouds with normals (built once), for residuals of frame ``i+1`` against ``i``."""

    def __init__(self, points: list[np.ndarray], planar: bool, distance: float, floor: float = 0.0) -> None:
        """``distance``: the correspondence distance (m); ``floor``: the least noise a residual is taken to have
        (m)."""
        self.points, self.planar, self.distance, self.floor = points, planar, float(distance), float(floor)
        self._clouds: dict[int, Cloud] = {}

    def cloud(self, i: int) -> Cloud:
        if i not in self._clouds:
            self._clouds[i] = Cloud(np.asarray(self.points[i]), self.planar, 2.0 * self.distance)
        return self._clouds[i]

    def residual(self, i: int, relative: np.ndarray) -> tuple[float, int]:
        """Rms point-to-plane residual (m) of frame ``i+1`` placed at ``relative`` in frame ``i``, and how many of
        its points found a neighbour within the distance (:func:`~dm2_backend.algorithms.gates.plane_residual`)."""
        return plane_residual(self.cloud(i + 1), self.cloud(i), relative, self.distance)

    def release(self, keep: set[int]) -> None:
        """Drop the clouds of frames not in ``keep``."""
        for i in [i for i in self._clouds if i not in keep]:
            del self._clouds[i]


class StepJudge:
    """Judges trajectories' steps against fixed ``references`` (name -> step i -> the relative pose of frame i+1
    in frame i): the references' residuals are computed once, on first use."""

    def __init__(self, pairs: FramePairs, references: dict[str, dict[int, np.ndarray]]) -> None:
        self.pairs, self.references = pairs, references
        self._best: dict[int, tuple[float, str, np.ndarray]] = {}

    def best_reference(self, i: int) -> tuple[float, str, np.ndarray]:
        """The reference step of lowest residual: (residual, name, relative pose); residual inf where none."""
        if i not in self._best:
            best = (float("inf"), "", np.eye(4))
            for name, by_step in self.references.items():
                if i in by_step:
                    value, _ = self.pairs.residual(i, by_step[i])
                    if value < best[0]:
                        best = (value, name, by_step[i])
            self._best[i] = best
        return self._best[i]

    def check(self, poses: np.ndarray) -> StepCheck:
        """Every step of ``poses``; the sequence's spread is taken over the steps judged."""
        rows, squares, points = [], 0.0, 0
        for i in range(len(poses) - 1):
            self.pairs.release({i, i + 1})
            r = plane_residuals(self.pairs.cloud(i + 1), self.pairs.cloud(i), se3.relative(poses[i], poses[i + 1]),
                                self.pairs.distance)
            on = np.isfinite(r)
            own = float(np.sqrt(np.mean(r[on] ** 2))) if on.any() else float("inf")
            squares += float(np.sum(r[on] ** 2)) + (len(r) - int(on.sum())) * self.pairs.distance**2
            points += len(r)
            rows.append((i, own, int(on.sum()), *self.best_reference(i)))
        self.pairs.release(set())
        fit = float(np.sqrt(squares / points)) if points else float("nan")
        rows = [r for r in rows if r[2] >= MIN_MATCHED and np.isfinite(r[1]) and 0 < r[3] < np.inf]
        if not rows:
            empty = np.zeros(0)
            return StepCheck(np.zeros(0, int), empty, empty, (), np.zeros((0, 4, 4)), empty, np.zeros(0, int), 0.0,
                             np.zeros(0, bool), fit)
        idx, own, matched, ref = (np.array([r[k] for r in rows]) for k in range(4))
        poses_ref = np.stack([r[5] for r in rows])
        excess = own**2 / ref**2 - 1.0
        threshold = spread_threshold(excess[own != ref])
        contradicted = np.zeros(len(rows), bool)
        for k in np.flatnonzero(excess > threshold):
            i = int(idx[k])
            step = se3.relative(poses[i], poses[i + 1])
            contradicted[k] = all(significantly_worse(self.pairs.cloud(i + 1), self.pairs.cloud(i), step, by_step[i],
                                                      self.pairs.distance)
                                  for by_step in self.references.values() if i in by_step)
            self.pairs.release(set())
        return StepCheck(idx.astype(int), own, ref, tuple(r[4] for r in rows), poses_ref, excess,
                         matched.astype(int), threshold, contradicted, fit)


def spread_threshold(excess: np.ndarray) -> float:
    """The median of ``excess`` plus :data:`RATIO` robust sigmas; 0 with fewer than :data:`MIN_STEPS` values."""
    if len(excess) < MIN_STEPS:
        return 0.0
    median = float(np.median(excess))
    return median + RATIO * 1.4826 * float(np.median(np.abs(excess - median)))
