"""Whether each step of a trajectory agrees with the two frames' own data, judged without ground truth.

Each step ``i -> i+1`` is placed at the candidate's relative pose and at each reference step (the valid
registration of the pair, and the front end's odometry step): frame ``i+1``'s points are matched to frame ``i``'s
nearest points within the registration's fine correspondence distance, and their point-to-plane (planar scans:
point-to-line) residuals are taken, truncated at that distance (a point without a match costs the distance, so a
step that slides the frames apart costs what it lost). The step's *excess* is how much larger its mean truncated
square is than the best reference's, as a fraction of the latter. A step is *contradicted* when

- its excess lies more than :data:`SIGMAS` robust sigmas (1.4826 x the median absolute deviation) above the median
  excess of the steps that differ from their reference (fewer than :data:`MIN_STEPS` such steps: no spread is
  taken), and
- the two frames fit every reference better than the candidate beyond chance, point by point
  (:func:`~dm2_backend.algorithms.gates.significantly_worse`): a registration can slide into a spurious minimum
  along a corridor, where the odometry's step, which the candidate keeps, fits the frames as well.

Steps whose references match fewer than :data:`~dm2_backend.algorithms.gates.MIN_MATCHED` points are not judged.
Why each rule: ``docs/decisions/0001-step-guard.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.algorithms.common import Cloud
from dm2_backend.algorithms.gates import MIN_MATCHED, plane_residuals, significantly_worse, truncated_squares
from dm2_backend.kernel.geometry import se3

#: a step whose excess lies more than this many robust sigmas above the sequence's median excess stands out
SIGMAS = 10.0
#: the fewest steps the sequence's spread is taken over; with fewer the point-by-point test judges alone
MIN_STEPS = 20

REGISTRATION = "registration"
ODOMETRY = "odometry"


@dataclass(frozen=True)
class StepCheck:
    """Per judged step ``steps[k]`` (frame ``steps[k]`` to the next): the candidate's truncated rms residual, the
    best reference's and which reference that was, the excess, and whether the data contradicts the step."""

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
                "matched": self.matched.tolist(), "contradicted": self.steps[self.contradicted].tolist()}


class FramePairs:
    """The frames' points as clouds with normals (built when needed), for residuals of frame ``i+1`` against ``i``."""

    def __init__(self, points: list[np.ndarray], planar: bool, distance: float, floor: float = 0.0) -> None:
        """``distance``: the correspondence distance (m); ``floor``: the least noise a residual is taken to have
        (m)."""
        self.points, self.planar, self.distance, self.floor = points, planar, float(distance), float(floor)
        self._clouds: dict[int, Cloud] = {}

    def cloud(self, i: int) -> Cloud:
        if i not in self._clouds:
            self._clouds[i] = Cloud(np.asarray(self.points[i]), self.planar, 2.0 * self.distance)
        return self._clouds[i]

    def residual(self, i: int, relative: np.ndarray) -> tuple[float, float, int]:
        """Frame ``i+1`` placed at ``relative`` in frame ``i``: the sum of its points' truncated squared residuals
        (m^2), the number of its points, and how many found a neighbour within the distance."""
        r = plane_residuals(self.cloud(i + 1), self.cloud(i), relative, self.distance)
        return float(truncated_squares(r, self.distance).sum()), len(r), int(np.isfinite(r).sum())

    def release(self, keep: set[int]) -> None:
        """Drop the clouds of frames not in ``keep``."""
        for i in [i for i in self._clouds if i not in keep]:
            del self._clouds[i]


class StepJudge:
    """Judges trajectories' steps against fixed ``references`` (name -> step i -> the relative pose of frame i+1
    in frame i): the references' residuals are computed once, on first use."""

    def __init__(self, pairs: FramePairs, references: dict[str, dict[int, np.ndarray]]) -> None:
        self.pairs, self.references = pairs, references
        self._best: dict[int, tuple[float, str, np.ndarray] | None] = {}

    def best_reference(self, i: int) -> tuple[float, str, np.ndarray] | None:
        """The reference step that fits the frames best: (truncated rms, name, relative pose); None where no
        reference matches :data:`~dm2_backend.algorithms.gates.MIN_MATCHED` points."""
        if i not in self._best:
            best = None
            for name, by_step in self.references.items():
                if i in by_step:
                    squares, points, matched = self.pairs.residual(i, by_step[i])
                    rms = float(np.sqrt(squares / points)) if points else float("inf")
                    if matched >= MIN_MATCHED and (best is None or rms < best[0]):
                        best = (rms, name, by_step[i])
            self._best[i] = best
        return self._best[i]

    def fit(self, poses: np.ndarray) -> float:
        """How well all the steps of ``poses`` fit their frames: the truncated rms residual (m) over every point of
        every second frame (inf for poses that are not finite, NaN for fewer than two frames)."""
        return self._residuals(poses)[1]

    def check(self, poses: np.ndarray) -> StepCheck:
        """Every step of ``poses`` judged; the sequence's spread is taken over the steps judged."""
        rows, fit = self._residuals(poses)
        if not rows:
            empty = np.zeros(0)
            return StepCheck(np.zeros(0, int), empty, empty, (), np.zeros((0, 4, 4)), empty, np.zeros(0, int), 0.0,
                             np.zeros(0, bool), fit)
        idx, own, matched, ref = (np.array([r[k] for r in rows]) for k in range(4))
        steps, ref_steps = np.stack([r[6] for r in rows]), np.stack([r[5] for r in rows])
        excess = own**2 / np.maximum(ref, 1e-12) ** 2 - 1.0
        differ = ~np.all(np.isclose(steps, ref_steps, rtol=0.0, atol=1e-12), axis=(1, 2))
        threshold = spread_threshold(excess[differ])
        contradicted = np.zeros(len(rows), bool)
        for k in np.flatnonzero(differ & (excess > threshold)):
            i = int(idx[k])
            contradicted[k] = all(significantly_worse(self.pairs.cloud(i + 1), self.pairs.cloud(i), steps[k],
                                                      by_step[i], self.pairs.distance)
                                  for by_step in self.references.values() if i in by_step)
            self.pairs.release(set())
        return StepCheck(idx.astype(int), own, ref, tuple(r[4] for r in rows), ref_steps, excess,
                         matched.astype(int), threshold, contradicted, fit)

    def _residuals(self, poses: np.ndarray) -> tuple[list[tuple], float]:
        """Per step with a reference: (step, truncated rms, matched points, the best reference's rms, its name,
        its relative pose, the candidate's relative pose); and the fit of all the steps."""
        poses = np.asarray(poses, dtype=np.float64)
        if len(poses) < 2:
            return [], float("nan")
        if not np.isfinite(poses).all():
            return [], float("inf")
        rows, squares, points = [], 0.0, 0
        for i in range(len(poses) - 1):
            self.pairs.release({i, i + 1})
            step = se3.relative(poses[i], poses[i + 1])
            total, n, matched = self.pairs.residual(i, step)
            squares, points = squares + total, points + n
            best = self.best_reference(i)
            if best is not None and n:
                rows.append((i, float(np.sqrt(total / n)), matched, *best, step))
        self.pairs.release(set())
        return rows, float(np.sqrt(squares / points)) if points else float("nan")


def spread_threshold(excess: np.ndarray) -> float:
    """The median of ``excess`` plus :data:`SIGMAS` robust sigmas; 0 with fewer than :data:`MIN_STEPS` values."""
    if len(excess) < MIN_STEPS:
        return 0.0
    median = float(np.median(excess))
    return median + SIGMAS * 1.4826 * float(np.median(np.abs(excess - median)))
