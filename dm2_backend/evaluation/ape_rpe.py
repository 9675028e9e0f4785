"""APE and RPE computed through the evo library, so the numbers equal ``evo_ape`` / ``evo_rpe``.

Association: by timestamps (``evo.core.sync.associate_trajectories`` with ``max_diff``) when both
trajectories have them, by index otherwise when the counts agree (different counts are refused unless
``by_index`` forces the first min(N, M) poses). Alignment of the estimate onto the
ground truth: ``se3`` / ``sim3`` (Umeyama, evo's ``align``), ``none``, or evo's ``align_origin``.
Translation errors in metres, rotation errors in degrees (evo's ``rotation_angle_deg`` relation).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from evo import EvoException
from evo.core import lie_algebra, metrics, sync
from evo.core.geometry import accumulated_distances
from evo.core.result import Result
from evo.core.trajectory import PosePath3D, PoseTrajectory3D

from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.runtime.errors import InputError

ALIGN_MODES = ("se3", "sim3", "none")
DELTA_UNITS = {"f": metrics.Unit.frames, "m": metrics.Unit.meters}
#: statistics reported for every evo metric (evo's names)
STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")
_RELATIONS = {
    "trans": (metrics.PoseRelation.translation_part, "m"),
    "rot": (metrics.PoseRelation.rotation_angle_deg, "deg"),
}


@dataclass
class MetricResult:
    """One evo metric: its statistics, the per-pair errors and evo's own ``Result`` (for ``evo_res``)."""

    key: str  # ape_trans, ape_rot, rpe_trans, rpe_rot
    title: str
    unit: str  # "m" or "deg"
    stats: dict[str, float]
    errors: np.ndarray
    result: Result

    @property
    def count(self) -> int:
        return len(self.errors)


@dataclass
class PoseErrors:
    """APE and RPE of one estimate against the ground truth, with how the two were associated and aligned."""

    ref: PosePath3D  # associated ground truth
    est: PosePath3D  # associated estimate, after alignment
    est_raw: np.ndarray  # (N,4,4) associated estimate poses before alignment
    association: str  # "time" or "index"
    n_gt: int
    n_est: int
    max_diff: float | None
    align: str
    align_origin: bool
    alignment: np.ndarray | None  # 4x4 Sim(3) applied to the estimate (None when not aligned)
    scale: float
    metrics: dict[str, MetricResult]

    @property
    def n_matched(self) -> int:
        return self.ref.num_poses


def to_evo(traj: Trajectory, name: str | None = None) -> PosePath3D:
    """evo's trajectory type for a :class:`Trajectory` (``PoseTrajectory3D`` when it has timestamps)."""
    poses = [np.array(T) for T in traj.poses]
    if traj.timestamps is not None:
        return PoseTrajectory3D(poses_se3=poses, timestamps=traj.timestamps.copy(), name=name)
    return PosePath3D(poses_se3=poses, name=name)


def associate(
    ref: PosePath3D, est: PosePath3D, max_diff: float, source: str | Path | None = None, by_index: bool = False
) -> tuple[PosePath3D, PosePath3D, str]:
    """Associated copies of ``(ref, est)`` and the mode, ``"time"`` or ``"index"``. By index (``by_index``, or
    a side without stamps) the counts must agree unless ``by_index`` forces it (the first min(N, M) poses)."""
    if not by_index and isinstance(ref, PoseTrajectory3D) and isinstance(est, PoseTrajectory3D):
        try:
            ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
        except sync.SyncException:
            raise InputError(
                source, f"no pose within {max_diff} s of a ground-truth timestamp (see --max-diff)"
            ) from None
        return ref, est, "time"
    if ref.num_poses != est.num_poses and not by_index:
        missing = "the estimate has" if isinstance(ref, PoseTrajectory3D) else "the ground truth has"
        if not isinstance(ref, PoseTrajectory3D) and not isinstance(est, PoseTrajectory3D):
            missing = "neither has"
        raise InputError(source, f"{est.num_poses} poses against {ref.num_poses} of the ground truth and {missing} "
                                 "no timestamps to associate them by; give the stamps (--est-times / --gt-times) "
                                 f"or --by-index to compare the first {min(ref.num_poses, est.num_poses)} of each")
    n = min(ref.num_poses, est.num_poses)
    ref, est = copy.deepcopy(ref), copy.deepcopy(est)
    ref.reduce_to_ids(np.arange(n))
    est.reduce_to_ids(np.arange(n))
    return ref, est, "index"


def align_estimate(
    ref: PosePath3D, est: PosePath3D, align: str, align_origin: bool
) -> tuple[np.ndarray | None, float]:
    """Align ``est`` in place onto ``ref`` as evo does; return the Sim(3) matrix applied and the scale."""
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; choices: {', '.join(ALIGN_MODES)}")
    if align_origin and align != "none":
        raise ValueError("align_origin excludes se3/sim3 alignment (as in evo)")
    if align != "none":
        r, t, s = est.align(ref, correct_scale=align == "sim3")
        return lie_algebra.sim3(r, t, s), float(s)
    if align_origin:
        return est.align_origin(ref), 1.0
    return None, 1.0


def _title_suffix(align: str, align_origin: bool) -> str:
    if align == "se3":
        return "\n(with SE(3) Umeyama alignment)"
    if align == "sim3":
        return "\n(with Sim(3) Umeyama alignment)"
    return "\n(with origin alignment)" if align_origin else "\n(not aligned)"


def _add_arrays(res: Result, ref: PosePath3D, est: PosePath3D, alignment: np.ndarray | None) -> None:
    """The extra arrays evo's CLI stores in its result archives."""
    if isinstance(est, PoseTrajectory3D):
        res.add_np_array("seconds_from_start", est.timestamps - est.timestamps[0])
        res.add_np_array("timestamps", est.timestamps)
        res.add_np_array("distances_from_start", ref.distances)
        res.add_np_array("distances", est.distances)
    if alignment is not None:
        res.add_np_array("alignment_transformation_sim3", alignment)


def _process(metric: metrics.PE, data: tuple[PosePath3D, PosePath3D]) -> None:
    """evo's ``process_data``. For rotation angles evo calls scipy once per matrix (about 2 ms each); here
    evo computes the error poses E and the angles come from one batched call of the same evo function
    (``lie_algebra.sst_rotation_from_matrix(...).as_rotvec()``), with evo's SO(3) check: same numbers."""
    if metric.pose_relation is not metrics.PoseRelation.rotation_angle_deg:
        metric.process_data(data)
        return
    metric.pose_relation = metrics.PoseRelation.full_transformation
    try:
        metric.process_data(data)
    finally:
        metric.pose_relation = metrics.PoseRelation.rotation_angle_deg
    R = np.asarray(metric.E, dtype=np.float64).reshape(-1, 4, 4)[:, :3, :3]
    ok = np.isclose(np.linalg.det(R), 1.0, atol=1e-6) & np.isclose(
        np.swapaxes(R, 1, 2) @ R, np.eye(3), atol=1e-6).all(axis=(1, 2))
    if not ok.all():
        raise lie_algebra.LieAlgebraException(
            f"error pose {int(np.argmin(ok))}: matrix is not a valid SO(3) group element")
    rotvec = lie_algebra.sst_rotation_from_matrix(R).as_rotvec()
    metric.error = np.abs(np.rad2deg(np.linalg.norm(rotvec, axis=1)))


def _package(key: str, metric: metrics.PE, unit: str, suffix: str, names: tuple[str, str]) -> MetricResult:
    res = metric.get_result(*names)
    title = str(metric) + suffix
    res.info["title"] = title
    stats = {k: float(res.stats[k]) for k in STAT_KEYS}
    return MetricResult(key, title, unit, stats, np.asarray(res.np_arrays["error_array"]), res)


def _ape(ref, est, part: str, suffix: str, names, alignment) -> MetricResult:
    relation, unit = _RELATIONS[part]
    metric = metrics.APE(relation)
    _process(metric, (ref, est))
    out = _package(f"ape_{part}", metric, unit, suffix, names)
    _add_arrays(out.result, ref, est, alignment)
    return out


def _rpe(ref, est, part: str, delta: float, delta_unit: str, suffix: str, names, alignment) -> MetricResult:
    relation, unit = _RELATIONS[part]
    metric = metrics.RPE(relation, delta, DELTA_UNITS[delta_unit], 0.1, False, False)
    _process(metric, (ref, est))
    out = _package(f"rpe_{part}", metric, unit, suffix, names)
    ids = np.array([0, *metric.delta_ids])  # as evo_rpe: the poses of each pair's end, plus the first
    if isinstance(est, PoseTrajectory3D):
        stamps = est.timestamps[ids]
        out.result.add_np_array("seconds_from_start", (stamps - stamps[0])[1:])
        out.result.add_np_array("timestamps", stamps[1:])
        out.result.add_np_array("distances_from_start", accumulated_distances(ref.positions_xyz[ids])[1:])
        out.result.add_np_array("distances", accumulated_distances(est.positions_xyz[ids])[1:])
    if alignment is not None:
        out.result.add_np_array("alignment_transformation_sim3", alignment)
    return out


def evaluate_poses(
    gt: Trajectory,
    est: Trajectory,
    *,
    align: str = "se3",
    align_origin: bool = False,
    max_diff: float = 0.01,
    delta: float = 1.0,
    delta_unit: str = "f",
    names: tuple[str, str] = ("reference", "estimate"),
    source: str | Path | None = None,
    by_index: bool = False,
) -> PoseErrors:
    """APE and RPE (translation m, rotation deg) of ``est`` against ``gt``; ``source`` names the estimate
    in errors; ``by_index``: pair the poses in order, whatever their stamps and counts. Raises
    :class:`InputError` when nothing associates or evo rejects the data."""
    if delta_unit not in DELTA_UNITS:
        raise ValueError(f"unknown delta unit {delta_unit!r}; choices: {', '.join(DELTA_UNITS)}")
    if by_index:  # stamps play no part
        gt, est = replace(gt, timestamps=None), replace(est, timestamps=None)
    ref, est_e, mode = associate(to_evo(gt, names[0]), to_evo(est, names[1]), max_diff, source, by_index)
    suffix = _title_suffix(align, align_origin)
    raw = np.array(est_e.poses_se3)
    try:
        alignment, scale = align_estimate(ref, est_e, align, align_origin)
        results = {}
        for part in _RELATIONS:
            results[f"ape_{part}"] = _ape(ref, est_e, part, suffix, names, alignment)
        for part in _RELATIONS:
            results[f"rpe_{part}"] = _rpe(ref, est_e, part, delta, delta_unit, suffix, names, alignment)
    except EvoException as exc:
        raise InputError(source, f"evaluation failed on {ref.num_poses} associated poses: {exc}") from None
    return PoseErrors(
        ref=ref,
        est=est_e,
        est_raw=raw,
        association=mode,
        n_gt=len(gt),
        n_est=len(est),
        max_diff=max_diff if mode == "time" else None,
        align=align,
        align_origin=align_origin,
        alignment=alignment,
        scale=scale,
        metrics=results,
    )
