"""What the optimiser derives from the data, the start and its settings (the frozen :class:`OptimConfig`, the
``optimiser:`` section of the run configuration, defined in :mod:`dm2_backend.config.optimiser`)."""

from __future__ import annotations

from dataclasses import dataclass

from dm2_backend.config.optimiser import OptimConfig, switch
from dm2_backend.kernel.prepared import ScanScale


@dataclass(frozen=True)
class Lengths:
    """The optimiser's lengths (m; rad for ``step_rotation``): the config's, or derived from the data."""

    unit: float  # length unit of losses: 2 x point spacing
    finest_cell: float  # finest occupancy grid cell: = unit
    free_margin: float  # free-space samples stop this short of the hit: = unit
    chamfer_truncate: float  # 10 x unit
    step_translation: float  # Adam step on translation: unit / 10
    step_rotation: float  # Adam step on rotation: step_translation / range_median


@dataclass(frozen=True)
class PoseRegime:
    """Drift terms and the poses' learning rate (see :func:`pose_regime`)."""

    drift: bool
    lr_pose: float


@dataclass(frozen=True)
class LossRegime:
    """The losses and the pose warm-up (see :func:`loss_regime`)."""

    use_bce: bool
    use_consistency: bool
    chamfer_metric: str
    pose_warmup: float


@dataclass(frozen=True)
class Derived:
    """Everything the optimiser derived from the data, the start and the config's None values (the run report's
    ``derived``, in this order)."""

    unit: float
    finest_cell: float
    free_margin: float
    chamfer_truncate: float
    step_translation: float
    step_rotation: float
    drift: bool
    lr_pose: float
    #: median disagreement between the start's relative poses and the registrations (m; None: no valid pair)
    start_disagreement: float | None
    locally_accurate_start: bool
    use_bce: bool
    use_consistency: bool
    chamfer_metric: str
    pose_warmup: float
    #: a locally accurate 3D start, polished (see :func:`loss_regime`)
    polish: bool
    points_per_frame: int
    #: an epoch disagreeing more than this with the registrations has diverged and is never selected (m)
    max_disagreement: float | None
    epochs: int
    first_order: bool
    pose_warmup_steps: int


def sampled_points(cfg: OptimConfig, frames_max_points: int, planar: bool) -> int:
    """Points per frame the optimiser samples (``points_per_frame`` None: see its comment)."""
    if cfg.points_per_frame is not None:
        return cfg.points_per_frame
    return min(frames_max_points, 512) if not planar and cfg.start in ("auto", "graph") else 256


def loss_regime(cfg: OptimConfig, planar: bool, polish: bool) -> LossRegime:
    """The losses where the config leaves them None. From a locally accurate 3D start (the pose-graph solution,
    or poses that ``loops3d`` closed) the optimiser polishes: the start already satisfies the pairwise
    registrations, so the consistency loss only holds the poses there, and the occupancy field's finest cell
    (memory-bound) is coarser than the corrections left, so its BCE blurs them; the Chamfer distance along the
    surface normals sharpens the map (docs/decisions/0014-first-order-optimiser-defaults.md)."""
    return LossRegime(
        use_bce=switch(cfg.use_bce, not polish),
        use_consistency=switch(cfg.use_consistency, not polish),
        chamfer_metric=cfg.chamfer_metric or ("point" if planar else "plane"),
        pose_warmup=cfg.pose_warmup if cfg.pose_warmup is not None else (1.0 if polish else 0.0),
    )


def derive(cfg: OptimConfig, scale: ScanScale, planar: bool = True) -> Lengths:
    """Fill the None lengths from the data's scale (Frames.scale). The unit is twice the point spacing: of the
    down-sampled frames in 2D; of the raw scans (at least the voxel) in 3D, where the frames are a subsample
    whose points lie several scan spacings apart. The Chamfer
    distance is truncated at ten units (one when polishing a locally accurate 3D start, see the trainer)."""
    spacing = max(scale.spacing or 0.0, scale.voxel or 0.0, 1e-3)
    if not planar and scale.spacing_raw:
        spacing = max(scale.spacing_raw, scale.voxel or 0.0, 1e-3)
    unit = cfg.unit or 2.0 * spacing
    step_t = cfg.step_translation or unit / 10.0
    return Lengths(
        unit=unit,
        finest_cell=cfg.finest_cell or unit,
        free_margin=cfg.free_margin or unit,
        chamfer_truncate=cfg.chamfer_truncate or 10.0 * unit,
        step_translation=step_t,
        step_rotation=cfg.step_rotation or step_t / max(scale.length, 1e-3),
    )


#: a voxel spans at least this many noise sigmas: its flatness test (thickness under a quarter of its width,
#: ``planes.FLATNESS``) passes a flat patch of range noise ``sigma`` from ``4 sqrt(12) sigma`` = 13.9 sigmas up;
#: twice that, so a wall is not flat in one round and rough in the next (a 2D laser's cells hold one or two
#: points: their means carry the whole range noise)
NOISE_WIDTHS = 28.0


def dense_voxel(cfg: OptimConfig, scale: ScanScale, noise: float | None = None) -> float:
    """The plane term's largest voxel: planar patches a few per median range, its finest quarter at least a
    point spacing, and at least :data:`NOISE_WIDTHS` times the range ``noise`` (m) where it is known (planar
    scans; docs/decisions/0008-dense-voxel-and-planar-information.md)."""
    if cfg.dense_voxel is not None:
        return cfg.dense_voxel
    spacing = scale.spacing_raw or scale.spacing or 0.0
    return max(scale.length / 8.0, 4.0 * spacing, NOISE_WIDTHS * (noise or 0.0), 1e-3)


def pose_regime(cfg: OptimConfig, accurate: bool, polish: bool = False) -> PoseRegime:
    """``drift`` and ``lr_pose`` where the config leaves them None: small steps without drift terms from a
    locally accurate start, smaller ones when polishing it in 3D (larger ones dip the map in the first pose
    epochs), full steps with drift terms from a drifting start
    (docs/decisions/0014-first-order-optimiser-defaults.md)."""
    lr = 1.0 if not accurate else (0.02 if polish else 0.05)
    return PoseRegime(
        drift=switch(cfg.drift, not accurate),
        lr_pose=cfg.lr_pose if cfg.lr_pose is not None else lr,
    )
