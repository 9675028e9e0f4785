"""The step guard: refine never returns a step that the two frames' own data contradicts.

After the dense stage every consecutive step of its result is judged against the pair's valid registration and
the front end's odometry step (:mod:`dm2_backend.evaluation.step_check`). The contradicted steps are held at the
reference their data fits best (an exact edge of :data:`HOLD` information:
:meth:`~dm2_backend.pose_graph.PoseGraph.holding`) and the dense stage solves again from its result; this repeats
while steps are contradicted, at most :data:`ROUNDS` times. A result that still has a contradicted step is not
returned: its start stands.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dm2_backend.algorithms.common import fine_distance, lengths
from dm2_backend.baselines.graph import valid_pairs
from dm2_backend.evaluation.step_check import ODOMETRY, REGISTRATION, FramePairs, StepCheck, StepJudge
from dm2_backend.geometry import se3
from dm2_backend.prepare.steps import Prepared

log = logging.getLogger(__name__)

#: information (1/m^2, 1/rad^2) of a held step: 1 mm, 1 mrad
HOLD = 1e6
#: at most this many times the contradicted steps are held and the stage solved again
ROUNDS = 4


@dataclass(frozen=True)
class Guarded:
    """The poses after the guard, their final :class:`StepCheck`, the steps held (step -> relative pose held) and
    one record per round of holding."""

    poses: np.ndarray
    check: StepCheck
    held: dict[int, np.ndarray] = field(default_factory=dict)
    rounds: tuple[dict, ...] = ()

    @property
    def clean(self) -> bool:
        """No step of ``poses`` is contradicted."""
        return self.check.count == 0

    def summary(self) -> dict:
        return {"held": sorted(self.held), "rounds": list(self.rounds), "contradicted": self.check.count,
                "check": self.check.summary()}


def judge_of(prep: Prepared) -> StepJudge:
    """The judge of a preparation's steps: its frames, the valid registrations of consecutive frames and the
    warm start's steps, the residuals taken within the registration's fine correspondence distance."""
    registration = prep.resolved.get("registration")
    fine = registration.options.get("max_distance") if registration is not None else None
    distance = float(fine or fine_distance(lengths(prep.frames)))
    registered = {a: edge.relative for (a, b), edge in valid_pairs(prep.topology, prep.pairwise, prep.frames).items()
                  if b == a + 1}
    warm = np.asarray(prep.warm_start, dtype=np.float64)
    odometry = dict(enumerate(se3.relative(warm[:-1], warm[1:])))
    return StepJudge(FramePairs(prep.frames.points, prep.frames.planar, distance),
                     {REGISTRATION: registered, ODOMETRY: odometry})


def guard(judge: StepJudge, poses: np.ndarray,
          resolve: Callable[[np.ndarray, dict[int, np.ndarray]], np.ndarray]) -> Guarded:
    """``poses`` judged step by step; while steps are contradicted (at most :data:`ROUNDS` times), those steps are
    added to the held ones and ``resolve(poses, held)`` solves again from ``poses`` with every held step fixed."""
    check = judge.check(poses)
    held: dict[int, np.ndarray] = {}
    rounds = []
    for r in range(ROUNDS):
        if not check.count:
            break
        bad = np.flatnonzero(check.contradicted)
        reach = 2**r - 1  # a held step hands its tension to its neighbours: each round holds a wider stretch
        for k in bad:
            for i in range(int(check.steps[k]) - reach, int(check.steps[k]) + reach + 1):
                if 0 <= i < len(poses) - 1 and i not in held:
                    held[i] = judge.best_reference(i)[2]
        log.info("step guard: %d step(s) contradicted by their frames: %s; held and solved again", len(bad),
                 check.describe())
        rounds.append({"contradicted": check.steps[bad].tolist(), "held": len(held)})
        poses = resolve(poses, held)
        check = judge.check(poses)
    return Guarded(poses, check, held, tuple(rounds))
