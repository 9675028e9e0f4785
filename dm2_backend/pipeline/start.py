"""Where ``dm2 refine``'s optimiser starts: the prepared poses, or the pose-graph solution over the same edges.

A pose graph (odometry + the pairwise registrations, solved by GTSAM with a Cauchy kernel: exactly ``dm2
baseline gtsam``) converges in a few Levenberg-Marquardt iterations to what the constraints say, further than
first-order DeepMapping2 steps from the loop-closed poses get. Starting from the graph's solution lets the map
losses refine what the constraints got wrong. The graph start is taken only when it keeps the sequence's steps
(no step that both the front end's odometry and the two frames' registration contradict:
:mod:`dm2_backend.evaluation.continuity`) and
its frames agree better than the prepared poses' with the planes the other frames make (the dense stage's cells:
:class:`DenseCells`; without the dense stage, its map is sharper by mean map entropy), both judged without ground
truth, so a graph that a clique of wrong registrations cut or bent does not start the optimiser; nor is a dense
result that cuts a step kept. Map entropy does not judge the start where the planes can: a map sharper in the mean
can be bent where the camera sees one corner (docs/decisions/0002-start-judged-by-planes.md).
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dm2_backend.algorithms.common import lengths, project_planar
from dm2_backend.algorithms.pairwise import COARSE
from dm2_backend.evaluation import continuity
from dm2_backend.evaluation.map_quality import MapSampler
from dm2_backend.kernel import gtsam_solver
from dm2_backend.kernel.graph_edges import InformationModel, build_graph, valid_pairs
from dm2_backend.kernel.planes import Cells, agreement_score, cells_from_scans
from dm2_backend.kernel.pose_graph import lift_planar_information
from dm2_backend.kernel.scans import DEPTH_CAMERA, ScanSequence
from dm2_backend.kernel.solver_options import SolverOptions
from dm2_backend.optim import depth_noise
from dm2_backend.optim.config import OptimConfig, dense_voxel
from dm2_backend.optim.dense import refine_dense
from dm2_backend.optim.dense_checkpoint import DENSE_CHECKPOINT
from dm2_backend.optim.depth_noise import RangeNoise
from dm2_backend.optim.odometry_noise import MeasuredNoise
from dm2_backend.optim.stop import Stop
from dm2_backend.pipeline import step_guard
from dm2_backend.prepare.steps import Prepared
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.memory import release_mapped

log = logging.getLogger(__name__)

#: the pose graph solved for the start: ``dm2 baseline gtsam``'s defaults
GRAPH_SOLVER = SolverOptions(robust="cauchy")
#: information (1/m^2, 1/rad^2) with which a planar graph's edges hold z, roll and pitch in the dense stage: a 1 mm,
#: 1 mrad step (the extruded walls hold roll and pitch as well; the result is projected back to the plane)
PLANAR_HOLD = 1e6


class StartKind(str, enum.Enum):
    """Which poses the optimiser starts from: the pose-graph solution, the prepared (loop-closed or warm-start)
    poses, or the front end's warm start where the dense stage's judge found it agrees best."""

    GRAPH = "graph"
    PREPARED = "prepared"
    WARM_START = "warm start"


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
    history: list[dict]  # one row per round (``optim.dense.DenseResult.history``)
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
                "stop_reason": self.stopped.reason.value, "history": self.history,
                "resumed_after_round": self.resumed_after_round,
                "odometry_noise": self.odometry_noise.summary() if self.odometry_noise else None,
                "agreement_m2": self.agreement_m2, "cuts": self.cuts.summary(), "step_guard": self.step_guard.summary(),
                "start_fit_m": self.start_fit_m, "returned": self.returned.value}


@dataclass(frozen=True)
class Start:
    """The optimiser's start: its :class:`StartKind` ``name``, why, and the evidence the choice was made on;
    ``dense`` what the dense stage did from there (None when it did not run; ``poses`` are then its result)."""

    poses: np.ndarray
    name: StartKind
    why: str
    map_entropy: dict[str, float] = field(default_factory=dict)  # candidate -> mean map entropy
    dense: DenseSummary | None = None
    graph_cuts: continuity.Cuts | None = None  # the pose-graph solution's cut steps, where it was solved
    #: candidate ("prepared", "graph") -> :meth:`DenseCells.agreement`, judged on those two's planes (the dense
    #: stage's own ``agreement_m2`` judges its start and result on theirs)
    agreement_m2: dict[str, float] = field(default_factory=dict)

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
        return {"name": self.name.value, "why": self.why, "map_entropy": self.map_entropy,
                "agreement_m2": self.agreement_m2, "dense": self.dense.summary() if self.dense else {},
                "cuts": {"graph": self.graph_cuts.summary()} if self.graph_cuts is not None else {}}


def sequence_cuts(prep: Prepared, poses: np.ndarray) -> continuity.Cuts:
    """The steps of ``poses`` that neither the front end's odometry (the warm start) nor the valid registration of
    the two frames explains (:func:`dm2_backend.evaluation.continuity.cuts`; the smallest cut: the registration's
    coarse correspondence distance, how far a scan-matching step slides)."""
    slip = COARSE * step_guard.correspondence_distance(prep)
    return continuity.cuts(poses, prep.warm_start, step_guard.consecutive_registrations(prep), slip,
                           lengths(prep.frames).range_median or 1.0)


def choose_start(prep: Prepared, cfg: OptimConfig, sampler: MapSampler | None,
                 judge: DenseCells | None = None) -> Start:
    """``cfg.start`` "prepared": the prepared poses; "graph": the pose-graph solution when its frames agree better
    with the planes the other frames make than the prepared poses' do (``judge``: the dense stage's cells; without
    them, when its map is sharper by map entropy; without a map sampler, or when the graph cannot be solved, see
    ``why``); "auto": graph for 3D data, prepared for planar data (2D laser logs: the loop-closed poses of
    ``loops`` are already a pose-graph solution in all three degrees of freedom, and the map losses refine them
    further than the graph over the pairwise registrations; docs/decisions/0002-start-judged-by-planes.md)."""
    prepared = prep.initial
    if cfg.start == "prepared":
        return Start(prepared, StartKind.PREPARED, "optimiser.start: prepared")
    if cfg.start == "auto" and prep.frames.planar:
        return Start(prepared, StartKind.PREPARED, "optimiser.start auto: planar data start from the prepared poses")
    model = InformationModel.from_resolved(prep.resolved)
    graph = build_graph(prep.frames, prepared, prep.topology, prep.pairwise, model)
    if graph.meta["loop_edges"] == 0:  # the odometry edges are the prepared poses' own steps
        return Start(prepared, StartKind.PREPARED, "no registration edges beyond the odometry: the graph is the start")
    try:
        solved = gtsam_solver.optimize(graph, GRAPH_SOLVER).poses
    except InputError as exc:
        log.warning("pose-graph start failed (%s); starting from the prepared poses", exc.message)
        return Start(prepared, StartKind.PREPARED, f"the pose graph could not be solved: {exc.message}")
    cut = sequence_cuts(prep, solved)
    if cut:
        log.warning("pose-graph start not taken: it cuts the sequence at %s", cut.describe())
        why = (f"the pose-graph solution cuts the sequence at {cut.describe()}, which neither the odometry nor the "
               "registration of those frames says")
        return Start(prepared, StartKind.PREPARED, why, graph_cuts=cut)
    agreement = judge.agreement({"prepared": prepared, "graph": solved}) if judge is not None else {}
    if agreement and all(np.isfinite(v) for v in agreement.values()):  # each frame against the others' planes
        graph_agrees = agreement["graph"] <= agreement["prepared"]
        log.info("start: the %s poses (frames' disagreement with the others' planes: prepared %.3g m2, graph %.3g m2)",
                 "graph" if graph_agrees else "prepared", agreement["prepared"], agreement["graph"])
        if graph_agrees:
            return Start(solved, StartKind.GRAPH, "the pose-graph solution's frames agree better with the planes the "
                         "others see", graph_cuts=cut, agreement_m2=agreement)
        return Start(prepared, StartKind.PREPARED, "the pose-graph solution's frames agree worse with the planes the "
                     "others see", graph_cuts=cut, agreement_m2=agreement)
    # no judge, or no plane seen by two frames to judge by: the maps' sharpness
    if sampler is None:
        return Start(solved, StartKind.GRAPH, "pose-graph solution (no map to compare)", graph_cuts=cut,
                     agreement_m2=agreement)
    scores = {"prepared": sampler.evaluate(prepared).entropy, "graph": sampler.evaluate(solved).entropy}
    if scores["graph"] <= scores["prepared"]:
        return Start(solved, StartKind.GRAPH, "the pose-graph solution makes the sharper map", scores,
                     graph_cuts=cut, agreement_m2=agreement)
    return Start(prepared, StartKind.PREPARED, "the pose-graph solution makes a blurrier map", scores,
                 graph_cuts=cut, agreement_m2=agreement)


def range_noise(prep: Prepared) -> float | None:
    """Planar scans' range noise across their lines (m): the median point-to-line rms of the valid registrations,
    over sqrt(2) (two scans' noise in each residual); None without (3D: the voxel rule does without it,
    docs/decisions/0008-dense-voxel-and-planar-information.md)."""
    if not prep.frames.planar:
        return None
    rms = [e.plane_rmse for e in valid_pairs(prep.topology, prep.pairwise, prep.frames).values()
           if e.hessian is not None and np.isfinite(e.plane_rmse)]
    return float(np.median(rms)) / np.sqrt(2.0) if rms else None


@dataclass
class DenseCells:
    """Every scan compressed into the dense stage's cells (:func:`cells_from_scans`), with the voxel of its planes
    and the planar scans' range noise (None for 3D); built once, for judging the start and for the stage (from the
    scans, config and seed the stage itself would use: nothing checks that they are)."""

    cells: Cells
    voxel: float
    noise: float | None
    seconds: float
    #: a depth camera's range noise, which weighs its cells (:mod:`dm2_backend.optim.depth_noise`)
    depth_noise: RangeNoise | None = None

    @classmethod
    def of(cls, scans: ScanSequence, prep: Prepared, cfg: OptimConfig, seed: int = 0,
           progress: bool = False) -> DenseCells:
        noise = range_noise(prep)
        voxel = dense_voxel(cfg, prep.frames.scale, noise)
        t = time.perf_counter()
        # 3D scans' cells lie along the beams; planar scans keep the cubic grid (docs/decisions/0003-beam-cells.md)
        cells = cells_from_scans(scans, voxel / 4.0, cfg.dense_cells_per_frame, cfg.dense_max_cells, seed, progress,
                                 keep_scatter=cfg.dense_cell_scatter)
        if prep.frames.planar:
            cells = cells.extruded(voxel)
        measured = None
        if scans.sensor == DEPTH_CAMERA and cfg.dense_depth_noise:
            measured = depth_noise.measure(scans, voxel / 4.0, cfg.dense_cells_per_frame)
            if measured is not None:
                cells = depth_noise.weighed(cells, measured)
                log.info("depth camera: %s; the dense stage weighs each cell by it", measured.describe())
        return cls(cells, voxel, noise, time.perf_counter() - t, measured)

    def agreement(self, candidates: dict[str, np.ndarray]) -> dict[str, float]:
        """How far each candidate's frames lie from the planes the other frames make (m^2, lower is better;
        :func:`~dm2_backend.kernel.planes.agreement_score`, judged on each candidate's planes in turn)."""
        return agreement_score(self.cells, candidates, self.voxel)


def dense_start(scans: ScanSequence, prep: Prepared, start: Start, cfg: OptimConfig, seed: int = 0,
                progress: bool = False, trace: Callable[[np.ndarray], float] | None = None,
                checkpoint_dir: Path | None = None, resume: bool = False,
                dense_cells: DenseCells | None = None) -> Start:
    """``start`` refined by the dense stage (``cfg.dense``): every scan's points against the planes many frames
    share, jointly with the pose graph's factors (:mod:`dm2_backend.optim.dense`); its checkpoint in
    ``checkpoint_dir``, continued with ``resume``; ``dense_cells``: the cells already built (else built here).
    Planar scans (2D lasers) see walls as lines: their cells are extruded into vertical walls a voxel tall, the
    planar graph is solved as an SE(3) one that holds z, roll and pitch
    (:meth:`~dm2_backend.kernel.pose_graph.PoseGraph.lifted_to_se3`), and the result is projected back to x, y, yaw."""
    if not cfg.dense:
        return start
    planar = prep.frames.planar
    built = DenseCells.of(scans, prep, cfg, seed, progress) if dense_cells is None else dense_cells
    cells, voxel, noise = built.cells, built.voxel, built.noise
    # each registration weighed by its own Hessian where the preparation recorded one (every planar one)
    graph = build_graph(prep.frames, prep.initial, prep.topology, prep.pairwise, InformationModel(use_hessians=True))
    if planar:
        graph = graph.lifted_to_se3(PLANAR_HOLD)
    release_mapped(prep.frames.points)  # the rounds read the cells, not the frames: their pages leave the memory
    checkpoint = checkpoint_dir / DENSE_CHECKPOINT if checkpoint_dir is not None else None
    result = refine_dense(cells, graph, start.poses, voxel, cfg.dense_rounds, progress=progress, trace=trace,
                          checkpoint=checkpoint, resume=resume, measure_odometry=cfg.dense_odometry_noise)
    poses = project_planar(result.poses) if planar else result.poses

    def resolve(poses: np.ndarray, held: dict[int, step_guard.Hold]) -> np.ndarray:
        steps = np.array(sorted(held))
        information = np.stack([held[s].information for s in steps])
        if planar:  # the graph was lifted to SE(3)
            information = lift_planar_information(information, PLANAR_HOLD)
        holding = graph.holding(steps, np.stack([held[s].relative for s in steps]), information)
        again = refine_dense(cells, holding, poses, voxel, cfg.dense_rounds, progress=progress, trace=trace,
                             measure_odometry=cfg.dense_odometry_noise).poses
        return project_planar(again) if planar else again

    judge = step_guard.judge_of(prep)
    guarded = step_guard.guard(judge, poses, resolve)
    poses = guarded.poses
    start_fit = judge.fit(start.poses)  # reported beside the result's (``step_guard.check.fit_m``)
    # never worse than where it started, judged without ground truth: each frame against the map the others make
    candidates = {Kept.WARM_START: prep.warm_start, Kept(start.name.value): start.poses, Kept.DENSE: poses}
    agreement = agreement_score(cells, {k.value: v for k, v in candidates.items()}, voxel,
                                judges=(start.name.value, Kept.DENSE.value))
    finite = {Kept(name): score for name, score in agreement.items() if np.isfinite(score)}
    # no plane seen by two frames (too few or too sparse scans): nothing to judge by, the start stands
    judged = len(finite) == len(agreement)
    chosen = min(finite, key=finite.get) if judged else Kept(start.name.value)
    reason = f"{chosen.value} agrees better" if judged else "no plane seen by two frames to judge by"
    cut = sequence_cuts(prep, poses)
    if chosen is Kept.DENSE and cut:  # its frames agree, its steps do not: the start stands
        log.warning("dense stage's result not kept: it cuts the sequence at %s", cut.describe())
        chosen, reason = Kept(start.name.value), f"it cuts the sequence at {cut.describe()}"
    if chosen is Kept.DENSE and not guarded.clean:  # held and solved again, a step is still contradicted
        log.warning("dense stage's result not kept: its frames contradict %s", guarded.check.describe())
        chosen, reason = Kept(start.name.value), f"its frames contradict {guarded.check.describe()}"
    dense = DenseSummary(voxel, noise, graph.meta["hessian_edges"], built.depth_noise, cells.size, len(cells),
                         built.seconds, result.seconds, result.history, result.stopped, result.resumed_after,
                         result.odometry, agreement, cut, guarded, start_fit, chosen)
    log.info("dense: %d cells of %.3g m and up, %s; %s; returned %s (frames' disagreement with the others' "
             "planes: %s)", len(cells), cells.size, result.stopped, _guard_text(guarded), chosen.value,
             ", ".join(f"{k} {v:.3g} m2" for k, v in agreement.items()))
    if chosen is not Kept.DENSE:
        return replace(start, poses=candidates[chosen], name=StartKind(chosen.value), dense=dense,
                       why=f"{start.why}; the dense stage's result was not kept ({reason})")
    return replace(start, poses=poses, dense=dense)


def _guard_text(guarded: step_guard.Guarded) -> str:
    """``step guard: 17 steps held (271-304, 448), none contradicted`` for the console."""
    if not guarded.held:
        return f"step guard: none of {len(guarded.check.steps)} steps contradicted by their frames"
    left = f"{guarded.check.count} still contradicted" if guarded.check.count else "none contradicted"
    return f"step guard: {len(guarded.held)} steps held ({spans(sorted(guarded.held))}), {left}"


def spans(steps: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``3-5, 9``."""
    out: list[list[int]] = []
    for s in steps:
        if out and s == out[-1][1] + 1:
            out[-1][1] = s
        else:
            out.append([s, s])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in out)
