"""How far scan matching can be trusted against the odometry it is fused with, measured on the data.

Over triples of consecutive frames (i, i+1, i+2) the pairwise matches close a cycle,
``T(i, i+2)^-1 T(i, i+1) T(i+1, i+2)``: what is left is the scan matching's disagreement with itself, the
odometry plays no part in it. The step match ``T(i, i+1)`` against the odometry's step is its disagreement with
the odometry. Per axis of the step (along, across, yaw), both are measured as robust spreads about zero
(``1.4826 x median |.|``, so a biased odometry counts against it), and the share of the disagreement with the
odometry that the scan matching's own inconsistency does not explain is the odometry's:

    weight = 1 - (cycle spread / disagreement spread)^2,   clipped to [0, 1].

A scan match is then taken as ``prediction (+) weight * (match (-) prediction)`` per axis: where scans are
sharp and the odometry slips (wheel odometry on a smooth floor) the weights are near 1 and the scan matches are
taken whole; where the scans themselves disagree from one match to the next as much as they disagree with the
odometry (long-range returns through glass and across halls, a precise odometry), they lean on the odometry.
The cycle's spread is taken as one match's noise (the three matches of a cycle share their frames and their
errors, so the independent-errors bound, a third of its variance, would trust scans that do not hold). Why:
docs/decisions/0015-scan-weights-from-match-cycles.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.algorithms.common import Cloud, project_planar
from dm2_backend.algorithms.icp import register
from dm2_backend.kernel.geometry import se3

#: at most this many triples of consecutive frames, spread evenly over the sequence
TRIPLES = 200
#: with fewer triples whose matches overlapped, there is no evidence and scan matches are taken whole
MIN_TRIPLES = 20
#: a match whose fitness is below this is not measured (it would be the overlap test's, not the noise's)
MIN_FITNESS = 0.3

AXES = ("along", "across", "yaw")


@dataclass(frozen=True)
class MatchWeights:
    """Per axis (along, across, yaw): the weight of a scan match against the odometry, and the spreads it came
    from (m, m, rad)."""

    weights: tuple[float, float, float]
    cycle_spread: tuple[float, float, float]
    disagreement_spread: tuple[float, float, float]
    triples: int

    @classmethod
    def whole(cls, triples: int = 0) -> MatchWeights:
        """Scan matches taken whole (no evidence either way)."""
        nan = (float("nan"),) * 3
        return cls((1.0, 1.0, 1.0), nan, nan, triples)

    @property
    def more_precise(self) -> str:
        """"odometry" where the odometry explains less than half the disagreement on every axis (its variance below
        the scan matching's), else "scan"."""
        return "odometry" if max(self.weights) < 0.5 else "scan"

    def blend(self, predicted: np.ndarray, match: np.ndarray) -> np.ndarray:
        """``predicted (+) weights * (match (-) predicted)`` for planar poses."""
        d = se3.to_xy_yaw(se3.relative(predicted, match)) * np.asarray(self.weights)
        return predicted @ se3.from_xy_yaw(d)

    def as_dict(self) -> dict:
        r = lambda v: [None if not np.isfinite(x) else round(float(x), 6) for x in v]  # noqa: E731
        return {"weights": r(self.weights), "cycle_spread": r(self.cycle_spread),
                "disagreement_spread": r(self.disagreement_spread), "triples": self.triples, "axes": list(AXES)}


def _spread(values: np.ndarray) -> np.ndarray:
    return 1.4826 * np.median(np.abs(values), axis=0)


def match_weights(points: list[np.ndarray], odometry: np.ndarray, fine: float, iterations: int = 30,
                  triples: int = TRIPLES) -> MatchWeights:
    """:class:`MatchWeights` of planar frames ``points`` against the planar ``odometry`` poses, from up to
    ``triples`` cycles of pairwise point-to-line matches (coarse pass at 4 ``fine``, then ``fine``)."""
    n = len(points)
    if n < 3:
        return MatchWeights.whole()
    starts = np.unique(np.linspace(0, n - 3, min(triples, n - 2)).astype(int))
    clouds: dict[int, Cloud] = {}

    def cloud(i: int) -> Cloud:
        if i not in clouds:
            clouds[i] = Cloud(points[i], True, 2.0 * fine)
        return clouds[i]

    def match(a: int, b: int) -> np.ndarray | None:
        init = se3.relative(odometry[a], odometry[b])
        m = register(cloud(b), cloud(a), init, (4.0 * fine, fine), "point-to-plane", iterations, 0.0)
        ok = np.isfinite(m.T).all() and m.fitness >= MIN_FITNESS
        return project_planar(m.T) if ok else None

    cycles, steps = [], []
    for i in starts:
        i = int(i)
        t01, t12, t02 = match(i, i + 1), match(i + 1, i + 2), match(i, i + 2)
        if t01 is None or t12 is None or t02 is None:
            continue
        cycles.append(se3.to_xy_yaw(np.linalg.inv(t02) @ t01 @ t12))
        steps.append(se3.to_xy_yaw(se3.relative(se3.relative(odometry[i], odometry[i + 1]), t01)))
        clouds.pop(i, None)
    if len(cycles) < MIN_TRIPLES:
        return MatchWeights.whole(len(cycles))
    c, d = _spread(np.array(cycles)), _spread(np.array(steps))
    w = np.where(d > 0, 1.0 - (c / np.where(d > 0, d, 1.0)) ** 2, 1.0)
    w = np.clip(w, 0.0, 1.0)
    return MatchWeights(tuple(float(x) for x in w), tuple(float(x) for x in c), tuple(float(x) for x in d),
                        len(cycles))
