"""The optimiser section of the run configuration (``optimiser:`` in the YAML config): one frozen model, each
field with the measured reason for its default. Validated once, when the config is read (``config.load``); the
values the optimiser derives from the data are in :mod:`dm2_backend.optim.config`."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class OptimConfig(BaseModel):
    """Defaults work without tuning: every length left as None is derived from the data (see
    ``optim.config.derive``). Strict types: an int is taken for a float, nothing else is converted."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    epochs: int = Field(12, ge=1)
    #: cap on optimisation steps: long sequences run fewer epochs (floor(max_steps / steps per epoch), at least
    #: one). More passes of noisy steps made ACES worse (icp warm start 0.716 m: 2 epochs 0.300, 12 epochs 0.75)
    #: while a 300-frame sequence keeps all 12 (228 steps). 0 = no cap
    max_steps: int = 1000
    #: ... but never fewer epochs than this (at most ``epochs``): at 10,000 frames the 1,000-step cap alone gave
    #: each frame a single visit, spent entirely in the pose warm-up when polishing a 3D start
    min_epochs: int = Field(2, ge=1)
    #: stop early once the optimisation has converged: after an epoch whose mean loss fell by less than this
    #: fraction of the previous epoch's and whose poses made no better map than the best so far (the start
    #: counts), two such epochs in a row (pose warm-up epochs do not count). 0 = run every epoch (the default: a
    #: 3D polish changes the loss by under 0.1 % an epoch while the map still sharpens; with 1e-3, sim-3d-500
    #: stopped after 4 of 12 epochs, its ATE still falling (0.0366 -> 0.0361 m), and returned its start)
    converge_tol: float = Field(0.0, ge=0)
    #: torch CPU threads; the steps are many small ops, where one thread beats two (0.15 s vs 1.0 s a step on
    #: 7k ACES frames while the other core is busy), 0 keeps torch's default
    threads: int = 1
    #: anchors (groups) per optimisation step
    batch_groups: int = 16
    #: "topology" (the paper), "temporal" (DeepMapping) or "random": which frames share a group
    batching: Literal["topology", "temporal", "random"] = "topology"
    #: "direct" per-frame corrections or "lnet" (PointNet, the paper's L-Net)
    pose_model: Literal["direct", "lnet"] = "direct"
    #: drift parameters: corrections that carry over to all later frames (see pose_model.py); None: on for a
    #: drifting start, off for a locally accurate one (see :func:`derive`): there noisy drift steps bend a
    #: good trajectory (ACES from 0.0365 m: 0.215 with, 0.0705 without)
    drift: bool | None = None
    #: step of each drift parameter relative to the direct ones (None: 1/sqrt(frames))
    drift_factor: float | None = None
    #: points per frame the losses see (None: 256 on planar data and from the prepared start; 512 of the
    #: down-sampled frame's points for 3D data, whose polished starts have errors below the spacing of a
    #: 256-point sample: simulated 3D LiDAR 500 frames from gtsam's 0.0378 m, 256 points 0.0368 and a map never
    #: sharper than the start, 512 points 0.0368, 1,024 points 0.0365 in twice the time)
    points_per_frame: int | None = None
    #: points per frame (a subset of the above) and free-space samples per ray for the occupancy BCE
    bce_points_per_frame: int = 64
    samples_per_ray: int = 2
    #: drop free-space samples within ``free_margin`` of any observed point of the step (rays grazing the
    #: ground or a wall). Off by default, as the paper samples along the rays only: measured mixed (simulated
    #: 3D LiDAR 500 frames 0.0567 -> 0.0492 m, 2,000 frames 0.305 -> 0.325, ACES 0.0358 -> 0.0360)
    free_clear: bool = False
    #: Chamfer distance between nearest points: "point" (the paper: Euclidean) or "plane" (along the
    #: neighbour's surface normal, estimated from its frame's points); None: plane for 3D data, point for
    #: planar (a 2D scan's neighbours lie on a line)
    chamfer_metric: Literal["point", "plane"] | None = None
    #: loss weights: total = bce + alpha * chamfer + beta * consistency (lengths in units of ``unit``)
    alpha: float = 1.0
    beta: float = 1.0
    #: None: on, except when polishing a locally accurate 3D start (see :func:`loss_regime`)
    use_bce: bool | None = None
    use_chamfer: bool = True
    use_consistency: bool | None = None
    #: robust kernel on each (anchor, neighbour) consistency distance d: "cauchy" uses c*log(1 + d/c) with c = unit,
    #: so a wrong pairwise registration pulls with a bounded force; "none" is the paper's plain mean
    consistency_kernel: Literal["cauchy", "none"] = "cauchy"
    #: Adam learning rate of the pose parameters (scales ``step_translation``/``step_rotation``); None: 1.0 from a
    #: drifting start, 0.05 from a locally accurate one, whose remaining errors are a few cells (ACES
    #: from 0.0365 m after 2 epochs: lr 1.0 0.0705 (1 epoch), 0.2 0.0376, 0.05 0.0359), 0.02 when polishing a
    #: locally accurate 3D start (see :func:`pose_regime`)
    lr_pose: float | None = None
    #: the start counts as locally accurate when it is loop-closed (``Topology.poses``) or when the median
    #: disagreement between its relative poses and the pairwise registrations is below this many units, i.e.
    #: half a point spacing (measured: RedKitchen icp warm start 0.13, simulated 3D LiDAR after loop closure
    #: 0.09 to 0.26; simulated random-walk odometry 0.34 to 2.75)
    accurate_below: float = 0.25
    #: which poses refine returns: "map" the sharpest map (lowest mean map entropy of the scans, no ground
    #: truth needed) among the start and every epoch, so refine never ends blurrier than its start; "loss"
    #: the epoch of lowest mean loss (the start is then never returned)
    select: Literal["map", "loss"] = "map"
    #: where the optimiser starts: "graph" the pose-graph solution over the prepared edges (what ``dm2
    #: baseline gtsam`` returns) when its frames agree better than the prepared poses' with the planes the other
    #: frames make (with the dense stage; without it, when its map is sharper), "prepared" the prepared
    #: poses (loop-closed, else the warm start), "auto" graph for 3D data, prepared for planar data. Measured:
    #: simulated 3D LiDAR 500 frames refine 0.055 m from prepared, 0.038 from graph (``loops`` corrects
    #: x, y, yaw only; the graph all six); ACES 0.0363 from prepared, 0.0421 from graph
    start: Literal["auto", "graph", "prepared"] = "auto"
    #: the dense multi-frame plane term, minimised by second-order steps over all poses jointly with the pose
    #: graph's factors before the first-order epochs (``dm2_backend.optim.dense``; a 2D scan's lines as walls);
    #: None or True: on, False: off
    dense: bool | None = None
    #: largest voxel of the plane term (m; non-flat voxels are split down to a quarter); None:
    #: max(median range / 8, 4 x the raw scans' point spacing, 28 x the range noise where the registrations
    #: measured it: every planar one, ``optim.config.dense_voxel``)
    dense_voxel: float | None = Field(None, gt=0)
    #: at most this many rounds (one Gauss-Newton step each, planes fitted again)
    dense_rounds: int = Field(30, ge=1)
    #: cells (each frame's points summed in cells of a quarter voxel) kept per frame and in all (time and memory
    #: grow with them: about 200 MiB and 20 s a round a million); a frame with more is summed into cells twice
    #: as large, then keeps a random subset. Simulated 32-beam LiDAR, 500 frames from gtsam's 0.0275 m: 2,048
    #: cells a frame 0.0010 m, 200 cells a frame (as at 7,500 frames) 0.0027 m
    dense_cells_per_frame: int = Field(2048, ge=1)
    dense_max_cells: int = Field(1_500_000, ge=1)
    #: which cells keep their scatter in the dense term (BALM2's exact point-to-plane cost of a point cluster):
    #: "thin" those thinner than a quarter of their width; "all"; "none" (each cell's points at its mean). A thick
    #: cell's thickness is mostly range noise along the beam, and its scatter turns each frame to lay its beams
    #: along the planes. Measured with refine (ATE m; all -> thin -> none): depth camera looking across a room
    #: from the truth 0.0121 -> 0.0068 -> 0.0061 and from its visual odometry 0.0111 -> 0.0066 -> 0.0098; walking
    #: round it from the odometry 0.0032 -> 0.0022 -> 0.0022; simulated street from the truth 0.00050 -> 0.00053
    #: -> 0.00054; real LiDAR keyframes' map entropy -4.3556 -> -4.3544 -> -4.3508; RedKitchen 0.0537 -> 0.0566 ->
    #: 0.0495 (its reference poses are KinectFusion's)
    dense_cell_scatter: Literal["all", "thin", "none"] = "thin"
    #: once the dense stage's planes settle, the front end's odometry edges are weighed by their own noise,
    #: measured against that solution (``dm2_backend.optim.odometry_noise``), and the stage goes on; False: the
    #: guessed weight of the pose graph throughout
    dense_odometry_noise: bool = True
    #: the first-order DeepMapping2 epochs (Adam on the M-Net BCE, Chamfer and consistency losses over anchor
    #: groups); None: on only when the dense stage did not run (after it, kept or not, they trade the steps the
    #: frames support for a sharper map)
    first_order: bool | None = None
    #: epochs at the start in which the poses hold still while the occupancy field learns the map (an
    #: untrained field pulls them anywhere); None: 1 when polishing a locally accurate 3D start, else 0
    pose_warmup: float | None = None
    lr_field: float = 1e-2
    lr_network: float = 1e-3
    #: final learning rate as a fraction of the initial one (cosine schedule)
    lr_final: float = 0.05
    grid_levels: int = 8
    grid_features: int = 2
    #: cells of the finest occupancy grid level (memory bound): about 1024^2 in 2D, 128^3 in 3D
    grid_max_cells: int = 2**21
    # derived from the data when None:
    unit: float | None = None  # length unit of losses (m): 2 x point spacing
    finest_cell: float | None = None  # finest occupancy grid cell (m): = unit
    free_margin: float | None = None  # free-space samples stop this short of the hit (m): = unit
    chamfer_truncate: float | None = None  # m: 10 x unit
    step_translation: float | None = None  # Adam step on translation (m): unit / 10
    step_rotation: float | None = None  # Adam step on rotation (rad): step_translation / range_median
