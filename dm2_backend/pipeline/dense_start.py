"""The dense stage from the chosen start: every scan compressed into cells (:class:`DenseCells`), the planes many
frames share minimised jointly with the pose graph's factors (:mod:`dm2_backend.optim.dense`), contradicted steps
held by the step guard, and the result kept only where its frames agree better with the others' planes than the
start's and it cuts no step (judged without ground truth)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dm2_backend.algorithms.common import project_planar
from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.kernel.graph_edges import InformationModel, build_graph, valid_pairs
from dm2_backend.kernel.planes import Cells, agreement_score, cells_from_scans
from dm2_backend.kernel.pose_graph import lift_planar_information
from dm2_backend.kernel.scans import DEPTH_CAMERA, ScanSequence
from dm2_backend.optim import depth_noise
from dm2_backend.optim.dense import refine_dense
from dm2_backend.optim.dense_checkpoint import DENSE_CHECKPOINT
from dm2_backend.optim.depth_noise import RangeNoise
from dm2_backend.optim.derived import dense_voxel
from dm2_backend.pipeline import step_guard
from dm2_backend.pipeline.start import DenseSummary, Kept, Start, StartKind, sequence_cuts
from dm2_backend.prepare.steps import Prepared
from dm2_backend.runtime.memory import release_mapped

log = logging.getLogger(__name__)

#: information (1/m^2, 1/rad^2) with which a planar graph's edges hold z, roll and pitch in the dense stage: a 1 mm,
#: 1 mrad step (the extruded walls hold roll and pitch as well; the result is projected back to the plane)
PLANAR_HOLD = 1e6


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
    begun = Kept(start.name.value)
    candidates = {Kept.WARM_START: prep.warm_start, begun: start.poses, Kept.DENSE: poses}
    agreement = agreement_score(cells, {k.value: v for k, v in candidates.items()}, voxel,
                                judges=(begun.value, Kept.DENSE.value))
    finite = {Kept(name): score for name, score in agreement.items() if np.isfinite(score)}
    # no plane seen by two frames (too few or too sparse scans): nothing to judge by, the start stands
    judged = len(finite) == len(agreement)
    chosen = min(finite, key=finite.get) if judged else begun
    reason = f"{chosen.value} agrees better" if judged else "no plane seen by two frames to judge by"
    cut = sequence_cuts(prep, poses)
    if chosen is Kept.DENSE and cut:  # its frames agree, its steps do not: the start stands
        log.warning("dense stage's result not kept: it cuts the sequence at %s", cut.describe())
        chosen, reason = begun, f"it cuts the sequence at {cut.describe()}"
    if chosen is Kept.DENSE and not guarded.clean:  # held and solved again, a step is still contradicted
        log.warning("dense stage's result not kept: its frames contradict %s", guarded.check.describe())
        chosen, reason = begun, f"its frames contradict {guarded.check.describe()}"
    dense = DenseSummary(voxel, noise, graph.built.hessian_edges, built.depth_noise, cells.size, len(cells),
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
