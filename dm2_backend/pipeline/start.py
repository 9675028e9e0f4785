"""Where ``dm2 refine``'s optimiser starts: the prepared poses, or the pose-graph solution over the same edges;
the start's typed record (:class:`Start`, with the dense stage's :class:`DenseSummary` once it ran from there).

A pose graph (odometry + the pairwise registrations, solved by GTSAM with a Cauchy kernel: exactly ``dm2
baseline gtsam``) converges in a few Levenberg-Marquardt iterations to what the constraints say, further than
first-order DeepMapping2 steps from the loop-closed poses get. Starting from the graph's solution lets the map
losses refine what the constraints got wrong. The graph start is taken only when it keeps the sequence's steps
(no step that both the front end's odometry and the two frames' registration contradict:
:mod:`dm2_backend.evaluation.continuity`) and its frames agree better than the prepared poses' with the planes
the other frames make (the dense stage's cells: :class:`~dm2_backend.pipeline.dense_start.DenseCells`; without
the dense stage, its map is sharper by mean map entropy), both judged without ground truth, so a graph that a
clique of wrong registrations cut or bent does not start the optimiser (nor is a dense result that cuts a step
kept: :mod:`dm2_backend.pipeline.dense_start`). Map entropy does not judge the start where the planes can: a map
sharper in the mean can be bent where the camera sees one corner (docs/decisions/0002-start-judged-by-planes.md).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from dm2_backend.algorithms.common import lengths
from dm2_backend.algorithms.pairwise import COARSE
from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.evaluation import continuity
from dm2_backend.evaluation.map_quality import MapSampler
from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel.graph_edges import InformationModel, build_graph
from dm2_backend.kernel.solver_options import SolverOptions
from dm2_backend.optim.dense_round import Round
from dm2_backend.optim.depth_noise import RangeNoise
from dm2_backend.optim.odometry_noise import MeasuredNoise
from dm2_backend.optim.stop import Stop
from dm2_backend.pipeline import step_guard
from dm2_backend.prepare.steps import Prepared
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)

#: the pose graph solved for the start: ``dm2 baseline gtsam``'s defaults
GRAPH_SOLVER = SolverOptions(robust="cauchy")


class StartKind(str, enum.Enum):
    """Which poses the optimiser starts from: the pose-graph solution, the prepared (loop-closed or warm-start)
    poses, or the front end's warm start where the dense stage's judge found it agrees best."""

    GRAPH = "graph"
    PREPARED = "prepared"
    WARM_START = "warm start"


class StartReason(str, enum.Enum):
    """What decided the start: the config, the data, or the evidence the candidates were judged by."""

    #: set by the caller (a test, a benchmark), not chosen here
    GIVEN = "given"
    #: ``optimiser.start: prepared``
    CONFIGURED = "configured"
    #: ``optimiser.start: auto`` on planar data
    PLANAR = "planar data"
    #: no registration edge beyond the odometry: the graph's solution is the prepared poses
    NO_LOOP_EDGES = "no loop edges"
    #: the pose graph could not be solved
    GRAPH_UNSOLVED = "graph unsolved"
    #: the graph's solution cuts the sequence (``graph_cuts``)
    GRAPH_CUTS = "graph cuts"
    #: judged by how the candidates' frames agree with the others' planes (``agreement_m2``)
    PLANES = "planes"
    #: judged by the candidates' mean map entropy (``map_entropy``)
    MAP_SHARPNESS = "map sharpness"
    #: nothing to judge the graph's solution by: it is taken
    NO_JUDGE = "no judge"


class Kept(str, enum.Enum):
    """The poses the dense stage's judge kept: its own result or one of the poses it was measured against."""

    DENSE = "dense"
    GRAPH = "graph"
    PREPARED = "prepared"
    WARM_START = "warm start"


@dataclass(frozen=True)
class DenseSummary:
    """What the dense stage did from a start: its cells, its rounds and why they ended, the step guard's verdict,
    how each candidate's frames agree with the others' planes, and which poses were kept."""

    voxel_m: float
    range_noise_m: float | None
    hessian_edges: int
    depth_noise: RangeNoise | None
    cell_m: float
    cells: int
    cells_seconds: float
    seconds: float
    history: list[Round]
    stopped: Stop
    resumed_after_round: int
    odometry_noise: MeasuredNoise | None
    agreement_m2: dict[str, float]  # candidate -> disagreement with the others' planes (m^2)
    cuts: continuity.Cuts
    step_guard: step_guard.Guarded
    start_fit_m: float  # the start's steps against the registrations (``step_guard.check.fit_m``)
    returned: Kept

    def summary(self) -> dict:
        """The record ``report.json`` keeps under ``start.dense``."""
        return {"voxel_m": self.voxel_m, "range_noise_m": self.range_noise_m, "hessian_edges": self.hessian_edges,
                "depth_noise": self.depth_noise.summary() if self.depth_noise is not None else None,
                "cell_m": self.cell_m, "cells": self.cells, "cells_seconds": self.cells_seconds,
                "seconds": self.seconds, "rounds": len(self.history), "stopped": self.stopped.detail,
                "stop_reason": self.stopped.reason.value, "history": [r.row() for r in self.history],
                "resumed_after_round": self.resumed_after_round,
                "odometry_noise": self.odometry_noise.summary() if self.odometry_noise else None,
                "agreement_m2": self.agreement_m2, "cuts": self.cuts.summary(), "step_guard": self.step_guard.summary(),
                "start_fit_m": self.start_fit_m, "returned": self.returned.value}


@dataclass(frozen=True)
class Start:
    """The optimiser's start: its :class:`StartKind` ``name``, why, and the evidence the choice was made on;
    ``dense`` what the dense stage did from there (None when it did not run; else ``poses`` are what its judge
    kept)."""

    poses: np.ndarray
    name: StartKind
    why: str
    reason: StartReason = StartReason.GIVEN
    map_entropy: dict[StartKind, float] = field(default_factory=dict)  # candidate -> mean map entropy
    dense: DenseSummary | None = None
    graph_cuts: continuity.Cuts | None = None  # the pose-graph solution's cut steps, where it was solved
    #: candidate -> :meth:`DenseCells.agreement`, judged on those two's planes (the dense stage's own
    #: ``agreement_m2`` judges its start and result on theirs)
    agreement_m2: dict[StartKind, float] = field(default_factory=dict)

    @property
    def refined(self) -> bool:
        """``poses`` are the dense stage's result."""
        return self.dense is not None and self.dense.returned is Kept.DENSE

    @property
    def dense_ran(self) -> bool:
        """The dense stage ran from this start (``poses`` are its result, or the start it did not improve on)."""
        return self.dense is not None

    @property
    def locally_accurate(self) -> bool:
        """The pose-graph solution, or the dense stage's result: both agree with the registrations."""
        return self.name is StartKind.GRAPH or self.refined

    def summary(self) -> dict:
        return {"name": self.name.value, "reason": self.reason.value, "why": self.why,
                "map_entropy": {k.value: v for k, v in self.map_entropy.items()},
                "agreement_m2": {k.value: v for k, v in self.agreement_m2.items()},
                "dense": self.dense.summary() if self.dense else {},
                "cuts": {"graph": self.graph_cuts.summary()} if self.graph_cuts is not None else {}}


class PlaneJudge(Protocol):
    """What judges candidate poses by the planes the other frames make (``dense_start.DenseCells``)."""

    def agreement(self, candidates: dict[str, np.ndarray]) -> dict[str, float]: ...


def sequence_cuts(prep: Prepared, poses: np.ndarray) -> continuity.Cuts:
    """The steps of ``poses`` that neither the front end's odometry (the warm start) nor the valid registration of
    the two frames explains (:func:`dm2_backend.evaluation.continuity.cuts`; the smallest cut: the registration's
    coarse correspondence distance, how far a scan-matching step slides)."""
    slip = COARSE * step_guard.correspondence_distance(prep)
    return continuity.cuts(poses, prep.warm_start, step_guard.consecutive_registrations(prep), slip,
                           lengths(prep.frames).range_median or 1.0)


def choose_start(prep: Prepared, cfg: OptimConfig, sampler: MapSampler | None,
                 judge: PlaneJudge | None = None) -> Start:
    """``cfg.start`` "prepared": the prepared poses; "graph": the pose-graph solution when its frames agree better
    with the planes the other frames make than the prepared poses' do (``judge``: the dense stage's cells; without
    them, when its map is sharper by map entropy; without a map sampler, or when the graph cannot be solved, see
    ``why``); "auto": graph for 3D data, prepared for planar data (2D laser logs: the loop-closed poses of
    ``loops`` are already a pose-graph solution in all three degrees of freedom, and the map losses refine them
    further than the graph over the pairwise registrations; docs/decisions/0002-start-judged-by-planes.md)."""
    prepared = prep.initial
    if cfg.start == "prepared":
        return Start(prepared, StartKind.PREPARED, "optimiser.start: prepared", StartReason.CONFIGURED)
    if cfg.start == "auto" and prep.frames.planar:
        return Start(prepared, StartKind.PREPARED, "optimiser.start auto: planar data start from the prepared poses",
                     StartReason.PLANAR)
    model = InformationModel.from_resolved(prep.resolved)
    graph = build_graph(prep.frames, prepared, prep.topology, prep.pairwise, model)
    if graph.built.loop_edges == 0:  # the odometry edges are the prepared poses' own steps
        return Start(prepared, StartKind.PREPARED, "no registration edges beyond the odometry: the graph is the start",
                     StartReason.NO_LOOP_EDGES)
    try:
        solved = gtsam_solver.optimize(graph, GRAPH_SOLVER).poses
    except InputError as exc:
        log.warning("pose-graph start failed (%s); starting from the prepared poses", exc.message)
        return Start(prepared, StartKind.PREPARED, f"the pose graph could not be solved: {exc.message}",
                     StartReason.GRAPH_UNSOLVED)
    cut = sequence_cuts(prep, solved)
    if cut:
        log.warning("pose-graph start not taken: it cuts the sequence at %s", cut.describe())
        why = (f"the pose-graph solution cuts the sequence at {cut.describe()}, which neither the odometry nor the "
               "registration of those frames says")
        return Start(prepared, StartKind.PREPARED, why, StartReason.GRAPH_CUTS, graph_cuts=cut)
    candidates = {StartKind.PREPARED: prepared, StartKind.GRAPH: solved}
    agreement = judge.agreement(candidates) if judge is not None else {}
    if agreement and all(np.isfinite(v) for v in agreement.values()):  # each frame against the others' planes
        graph_agrees = agreement[StartKind.GRAPH] <= agreement[StartKind.PREPARED]
        log.info("start: the %s poses (frames' disagreement with the others' planes: prepared %.3g m2, graph %.3g m2)",
                 "graph" if graph_agrees else "prepared", agreement[StartKind.PREPARED], agreement[StartKind.GRAPH])
        if graph_agrees:
            return Start(solved, StartKind.GRAPH, "the pose-graph solution's frames agree better with the planes the "
                         "others see", StartReason.PLANES, graph_cuts=cut, agreement_m2=agreement)
        return Start(prepared, StartKind.PREPARED, "the pose-graph solution's frames agree worse with the planes the "
                     "others see", StartReason.PLANES, graph_cuts=cut, agreement_m2=agreement)
    # no judge, or no plane seen by two frames to judge by: the maps' sharpness
    if sampler is None:
        return Start(solved, StartKind.GRAPH, "pose-graph solution (no map to compare)", StartReason.NO_JUDGE,
                     graph_cuts=cut, agreement_m2=agreement)
    scores = {kind: sampler.evaluate(poses).entropy for kind, poses in candidates.items()}
    if scores[StartKind.GRAPH] <= scores[StartKind.PREPARED]:
        return Start(solved, StartKind.GRAPH, "the pose-graph solution makes the sharper map",
                     StartReason.MAP_SHARPNESS, scores, graph_cuts=cut, agreement_m2=agreement)
    return Start(prepared, StartKind.PREPARED, "the pose-graph solution makes a blurrier map",
                 StartReason.MAP_SHARPNESS, scores, graph_cuts=cut, agreement_m2=agreement)
