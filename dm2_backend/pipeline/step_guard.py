"""The step guard: the dense stage's contradicted steps are held and solved again.

After the dense stage every consecutive step of its result is judged against the pair's valid registration and
the front end's odometry step (:mod:`dm2_backend.evaluation.step_check`). Each contradicted step, and its
neighbours in a stretch twice as wide each round, is held (:func:`hold_of`: an exact edge,
:meth:`~dm2_backend.kernel.pose_graph.PoseGraph.holding`) where its two frames fit best, with the information they give
(a direction they leave free, along a corridor or across one wall, is not held), and the dense stage solves again
from its result; this repeats while steps are contradicted, at most :data:`ROUNDS` times. :func:`guard` returns the
poses and the final verdicts; ``pipeline.dense_start.dense_start`` does not return a result with a contradicted
step left.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dm2_backend.algorithms.common import fine_distance, lengths, repeatable_registration
from dm2_backend.algorithms.icp import register
from dm2_backend.evaluation.step_check import ODOMETRY, REGISTRATION, FramePairs, StepCheck, StepJudge
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.graph_edges import InformationModel, hessian_information, rmse_floor, valid_pairs
from dm2_backend.prepare.steps import Prepared

log = logging.getLogger(__name__)

#: at most this many times the contradicted steps are held and the stage solved again
ROUNDS = 4


@dataclass(frozen=True)
class Hold:
    """A held step: the relative pose and its information (planar (3, 3) on x y yaw, else (6, 6) g2o order)."""

    relative: np.ndarray
    information: np.ndarray


@dataclass(frozen=True)
class GuardRound:
    """One round of holding: the steps contradicted before it and how many steps were held after it."""

    contradicted: tuple[int, ...]
    held: int

    def row(self) -> dict:
        return {"contradicted": list(self.contradicted), "held": self.held}


@dataclass(frozen=True)
class Guarded:
    """The poses after the guard, their final :class:`StepCheck`, the steps held (step -> :class:`Hold`), one
    record per round of holding and the guard's seconds."""

    poses: np.ndarray
    check: StepCheck
    held: dict[int, Hold] = field(default_factory=dict)
    rounds: tuple[GuardRound, ...] = ()
    seconds: float = 0.0

    @property
    def clean(self) -> bool:
        """No step of ``poses`` is contradicted."""
        return self.check.count == 0

    def summary(self) -> dict:
        return {"held": sorted(self.held), "rounds": [r.row() for r in self.rounds], "contradicted": self.check.count,
                "seconds": self.seconds, "check": self.check.summary()}


def correspondence_distance(prep: Prepared) -> float:
    """The registration's fine correspondence distance (m): its ``max_distance`` as configured, else the one it
    derives from the frames (:func:`~dm2_backend.algorithms.common.fine_distance`)."""
    registration = prep.resolved.get("registration")
    fine = registration.options.get("max_distance") if registration is not None else None
    return float(fine or fine_distance(lengths(prep.frames)))


def consecutive_registrations(prep: Prepared) -> dict[int, np.ndarray]:
    """Step i -> the valid registration of frame i+1 in frame i, where the preparation has one."""
    return {a: edge.relative for (a, b), edge in valid_pairs(prep.topology, prep.pairwise, prep.frames).items()
            if b == a + 1}


def judge_of(prep: Prepared) -> StepJudge:
    """The judge of a preparation's steps: its frames, the valid registrations of consecutive frames and the
    warm start's steps, the residuals taken within the registration's fine correspondence distance."""
    warm = np.asarray(prep.warm_start, dtype=np.float64)
    odometry = dict(enumerate(se3.relative(warm[:-1], warm[1:])))
    pairs = FramePairs(prep.frames.points, prep.frames.planar, correspondence_distance(prep),
                       rmse_floor(prep.frames, InformationModel()))
    return StepJudge(pairs, {REGISTRATION: consecutive_registrations(prep), ODOMETRY: odometry})


def hold_of(judge: StepJudge, i: int) -> Hold | None:
    """Step ``i`` where its two frames fit best: its best reference polished by point-to-plane (planar:
    point-to-line) ICP, with their point-to-plane Hessian over the variance of its residuals as the information
    (:func:`~dm2_backend.kernel.graph_edges.hessian_information`); None where no reference matches enough points to
    say where (the step is not held)."""
    best = judge.best_reference(i)
    if best is None:
        return None
    pairs = judge.pairs
    with repeatable_registration():
        match = register(pairs.cloud(i + 1), pairs.cloud(i), best[2], (pairs.distance,), "point-to-plane",
                         hessian=True)
    pairs.release(set())
    if match.hessian is None or not np.isfinite(match.T).all():
        return None
    return Hold(match.T, hessian_information(match.hessian, match.plane_rmse, pairs.floor))


def guard(judge: StepJudge, poses: np.ndarray, resolve: Callable[[np.ndarray, dict[int, Hold]], np.ndarray]
          ) -> Guarded:
    """``poses`` judged step by step; while steps are contradicted (at most :data:`ROUNDS` times), those steps are
    added to the held ones and ``resolve(poses, held)`` solves again from ``poses`` with every held step fixed."""
    t0 = time.perf_counter()
    check = judge.check(poses)
    held: dict[int, Hold] = {}
    rounds: list[GuardRound] = []
    for r in range(ROUNDS):
        if not check.count:
            break
        bad = np.flatnonzero(check.contradicted)
        reach = 2**r - 1  # a held step hands its tension to its neighbours: each round holds a wider stretch
        for k in bad:
            for i in range(int(check.steps[k]) - reach, int(check.steps[k]) + reach + 1):
                hold = hold_of(judge, i) if 0 <= i < len(poses) - 1 and i not in held else None
                if hold is not None:
                    held[i] = hold
        if not held:  # no contradicted step's frames say where it belongs
            break
        log.info("step guard: %d step(s) contradicted by their frames: %s; held and solved again", len(bad),
                 check.describe())
        rounds.append(GuardRound(tuple(check.steps[bad].tolist()), len(held)))
        poses = resolve(poses, held)
        check = judge.check(poses)
    return Guarded(poses, check, held, tuple(rounds), time.perf_counter() - t0)
