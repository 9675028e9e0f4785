"""The optimiser section of the run configuration (``optimiser:`` in the YAML config): one frozen model, each
field with the rule behind its default (the measurements that chose them: ``docs/decisions/``). Validated once,
when the config is read (``config.load``); the values the optimiser derives from the data are in
:mod:`dm2_backend.optim.derived`."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

#: a switch the optimiser can decide from the data and the start ("auto"; each field says how) or be told
Switch = Literal["auto", "on", "off"]
#: what a YAML file or an older dumped config may say for a switch: YAML 1.1 reads on/off as booleans
_SWITCH_WORDS = {True: "on", False: "off", None: "auto"}


def switch(value: Switch, auto: bool) -> bool:
    """A switch's effect: ``auto`` where it is "auto", else whether it is "on"."""
    return auto if value == "auto" else value == "on"


class OptimConfig(BaseModel):
    """Defaults work without tuning: every length left as None is derived from the data (see
    ``optim.derived.derive``). Strict types: an int is taken for a float, nothing else is converted."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    #: first-order epochs (passes over every anchor group), when they run (``first_order``)
    epochs: int = Field(12, ge=1)
    #: cap on optimisation steps: long sequences run fewer epochs (floor(max_steps / steps per epoch), at least
    #: one): more passes of noisy steps make a long sequence worse, while a short one keeps every epoch
    #: (docs/decisions/0014-first-order-optimiser-defaults.md). 0 = no cap
    max_steps: int = 1000
    #: ... but never fewer epochs than this (at most ``epochs``): at 10,000 frames the 1,000-step cap alone gives
    #: each frame a single visit, spent entirely in the pose warm-up when polishing a 3D start
    min_epochs: int = Field(2, ge=1)
    #: stop early once the optimisation has converged: after an epoch whose mean loss fell by less than this
    #: fraction of the previous epoch's and whose poses made no better map than the best so far (the start
    #: counts), two such epochs in a row (pose warm-up epochs do not count). 0 = run every epoch (the default: a
    #: 3D polish barely changes the loss while the map still sharpens;
    #: docs/decisions/0014-first-order-optimiser-defaults.md)
    converge_tol: float = Field(0.0, ge=0)
    #: torch CPU threads; the steps are many small ops, where one thread beats two (more so while the other core
    #: is busy; docs/decisions/0014-first-order-optimiser-defaults.md), 0 keeps torch's default
    threads: int = Field(1, ge=0)
    #: anchors (groups) per optimisation step
    batch_groups: int = Field(16, ge=1)
    #: "topology" (the paper), "temporal" (DeepMapping) or "random": which frames share a group
    batching: Literal["topology", "temporal", "random"] = "topology"
    #: "direct" per-frame corrections or "lnet" (PointNet, the paper's L-Net)
    pose_model: Literal["direct", "lnet"] = "direct"
    #: drift parameters: corrections that carry over to all later frames (see pose_model.py); auto: on for a
    #: drifting start, off for a locally accurate one (see :func:`derive`): there noisy drift steps bend a
    #: good trajectory (docs/decisions/0014-first-order-optimiser-defaults.md)
    drift: Switch = "auto"
    #: step of each drift parameter relative to the direct ones (None: 1/sqrt(frames))
    drift_factor: float | None = None
    #: points per frame the losses see (None: 256 on planar data and from the prepared start; 512 of the
    #: down-sampled frame's points for 3D data, whose polished starts have errors below the spacing of a
    #: 256-point sample; docs/decisions/0014-first-order-optimiser-defaults.md)
    points_per_frame: int | None = Field(None, ge=1)
    #: points per frame (a subset of the above) and free-space samples per ray for the occupancy BCE
    bce_points_per_frame: int = Field(64, ge=1)
    samples_per_ray: int = Field(2, ge=1, le=256)
    #: drop free-space samples within ``free_margin`` of any observed point of the step (rays grazing the
    #: ground or a wall). Off by default, as the paper samples along the rays only: it helps some sequences and
    #: not others (docs/decisions/0014-first-order-optimiser-defaults.md)
    free_clear: bool = False
    #: Chamfer distance between nearest points: "point" (the paper: Euclidean) or "plane" (along the
    #: neighbour's surface normal, estimated from its frame's points); None: plane for 3D data, point for
    #: planar (a 2D scan's neighbours lie on a line)
    chamfer_metric: Literal["point", "plane"] | None = None
    #: loss weights: total = bce + alpha * chamfer + beta * consistency (lengths in units of ``unit``)
    alpha: float = 1.0
    beta: float = 1.0
    #: auto: on, except when polishing a locally accurate 3D start (see :func:`loss_regime`)
    use_bce: Switch = "auto"
    #: the Chamfer term between each anchor and its neighbours
    use_chamfer: bool = True
    #: the consistency term against the pairwise registrations; auto: on, off when polishing a locally accurate
    #: 3D start (see :func:`loss_regime`)
    use_consistency: Switch = "auto"
    #: robust kernel on each (anchor, neighbour) consistency distance d: "cauchy" uses c*log(1 + d/c) with c = unit,
    #: so a wrong pairwise registration pulls with a bounded force; "none" is the paper's plain mean
    consistency_kernel: Literal["cauchy", "none"] = "cauchy"
    #: Adam learning rate of the pose parameters (scales ``step_translation``/``step_rotation``); None: 1.0 from a
    #: drifting start, 0.05 from a locally accurate one, whose remaining errors are a few cells, 0.02 when
    #: polishing a locally accurate 3D start (see :func:`pose_regime`;
    #: docs/decisions/0014-first-order-optimiser-defaults.md)
    lr_pose: float | None = None
    #: the start counts as locally accurate when it is loop-closed (``Topology.poses``) or when the median
    #: disagreement between its relative poses and the pairwise registrations is below this many units, i.e.
    #: half a point spacing: scan-matching front ends and loop-closed poses fall below it, random-walk odometry
    #: above (docs/decisions/0014-first-order-optimiser-defaults.md)
    accurate_below: float = 0.25
    #: which poses refine returns: "map" the sharpest map (lowest mean map entropy of the scans, no ground
    #: truth needed) among the start and every epoch, so refine never ends blurrier than its start; "loss"
    #: the epoch of lowest mean loss (the start is then never returned)
    select: Literal["map", "loss"] = "map"
    #: where the optimiser starts: "graph" the pose-graph solution over the prepared edges (what ``dm2
    #: baseline gtsam`` returns) when its frames agree better than the prepared poses' with the planes the other
    #: frames make (with the dense stage; without it, when its map is sharper), "prepared" the prepared
    #: poses (loop-closed, else the warm start), "auto" graph for 3D data, prepared for planar data (``loops``
    #: corrects x, y, yaw only, the graph all six; on 2D logs the loop-closed poses are already a pose-graph
    #: solution in all three; docs/decisions/0002-start-judged-by-planes.md)
    start: Literal["auto", "graph", "prepared"] = "auto"
    #: the dense multi-frame plane term, minimised by second-order steps over all poses jointly with the pose
    #: graph's factors before the first-order epochs (``dm2_backend.optim.dense``; a 2D scan's lines as walls);
    #: on by default (docs/decisions/0005-dense-stage-on-by-default.md)
    dense: bool = True
    #: largest voxel of the plane term (m; non-flat voxels are split down to a quarter); None:
    #: max(median range / 8, 4 x the raw scans' point spacing, 28 x the range noise where the registrations
    #: measured it: every planar one, ``optim.derived.dense_voxel``;
    #: docs/decisions/0008-dense-voxel-and-planar-information.md)
    dense_voxel: float | None = Field(None, gt=0)
    #: at most this many rounds (one Gauss-Newton step each, planes fitted again)
    dense_rounds: int = Field(30, ge=1)
    #: cells (each frame's points summed in cells of a quarter voxel) kept per frame and in all (time and memory
    #: grow with them: about 200 MiB and 20 s a round a million); a frame with more is summed into cells twice
    #: as large, then keeps a random subset; fewer cells a frame leave the dense stage further from its floor
    #: (docs/decisions/0005-dense-stage-on-by-default.md)
    dense_cells_per_frame: int = Field(2048, ge=1)
    #: ... and in all (the frames' share shrinks to fit it)
    dense_max_cells: int = Field(1_500_000, ge=1)
    #: which cells keep their scatter in the dense term (BALM2's exact point-to-plane cost of a point cluster):
    #: "thin" those thinner than a quarter of their width; "all"; "none" (each cell's points at its mean). A thick
    #: cell's thickness is mostly range noise along the beam, and its scatter turns each frame to lay its beams
    #: along the planes; a thin cell's scatter is the surface (docs/decisions/0004-thin-cell-scatter.md)
    dense_cell_scatter: Literal["all", "thin", "none"] = "thin"
    #: once the dense stage's planes settle, the front end's odometry edges are weighed by their own noise,
    #: measured against that solution (``dm2_backend.optim.odometry_noise``), and the stage goes on; False: the
    #: guessed weight of the pose graph throughout (docs/decisions/0007-odometry-noise-measured.md)
    dense_odometry_noise: bool = True
    #: True: a depth camera's cells weighed by its range noise, which grows with the square of the range, measured
    #: on its own frames (``dm2_backend.optim.depth_noise``); off by default: every point alike (it moved the
    #: real frames' result from any start to one place, but a locally exact input ended further from its reference;
    #: docs/decisions/0017-depth-cells-weighed-by-range-noise.md)
    dense_depth_noise: bool = False
    #: the first-order DeepMapping2 epochs (Adam on the M-Net BCE, Chamfer and consistency losses over anchor
    #: groups); auto: on only when the dense stage did not run (after it, kept or not, they trade the steps the
    #: frames support for a sharper map; docs/decisions/0006-first-order-off-after-dense.md)
    first_order: Switch = "auto"
    #: epochs at the start in which the poses hold still while the occupancy field learns the map (an
    #: untrained field pulls them anywhere); None: 1 when polishing a locally accurate 3D start, else 0
    pose_warmup: float | None = None
    #: Adam learning rate of the occupancy grid's features
    lr_field: float = Field(1e-2, gt=0)
    #: Adam learning rate of the occupancy network's weights
    lr_network: float = Field(1e-3, gt=0)
    #: final learning rate as a fraction of the initial one (cosine schedule)
    lr_final: float = 0.05
    #: resolution levels of the multi-resolution occupancy grid (M-Net's encoding)
    grid_levels: int = Field(8, ge=1)
    #: features per level of that grid
    grid_features: int = Field(2, ge=1)
    #: cells of the finest occupancy grid level (memory bound): about 1024^2 in 2D, 128^3 in 3D
    grid_max_cells: int = 2**21
    # derived from the data when None:
    unit: float | None = None  # length unit of losses (m): 2 x point spacing
    finest_cell: float | None = None  # finest occupancy grid cell (m): = unit
    free_margin: float | None = None  # free-space samples stop this short of the hit (m): = unit
    chamfer_truncate: float | None = None  # m: 10 x unit
    step_translation: float | None = None  # Adam step on translation (m): unit / 10
    step_rotation: float | None = None  # Adam step on rotation (rad): step_translation / range_median

    @field_validator("drift", "use_bce", "use_consistency", "first_order", mode="before")
    @classmethod
    def _switch_words(cls, value: object) -> object:
        """true/false/null (YAML's on/off among them) as "on"/"off"/"auto"."""
        return _SWITCH_WORDS[value] if value is None or isinstance(value, bool) else value

    @field_validator("dense", mode="before")
    @classmethod
    def _dense_null_is_on(cls, value: object) -> object:
        """A config dumped before the dense stage's switch became a plain bool says null for on."""
        return True if value is None else value
