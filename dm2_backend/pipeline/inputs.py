"""Read what a run needs: scans, the given trajectory, and optional ground truth or relations."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.config.schema import PluginSection, RunConfig
from dm2_backend.evaluation.relations import load_relations
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory
from dm2_backend.kernel.geometry import se3
from dm2_backend.kernel.scans import ScanSequence, SensorKind, associate_scans
from dm2_backend.kernel.trajectory import Trajectory, associate_by_time
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)

#: trajectories a scan source may carry that serve as the warm start when no --poses is given
CARRIED_WARM_START = ("odometry",)


@dataclass
class RunInputs:
    scans: ScanSequence
    given: Trajectory | None
    given_format: str | None
    given_path: Path | None
    gt: Trajectory | None = None
    relations: np.ndarray | None = None
    #: the scans the ground truth has a pose for, in the order of ``gt`` (None: every scan)
    gt_frames: np.ndarray | None = None
    #: the whole ``--poses`` trajectory when it has poses the scans were not paired with (a 100 Hz LIO for
    #: 10 Hz scans): the run also writes it corrected (``poses_full_rate_*``)
    given_full: Trajectory | None = None

    def at_gt(self, poses: np.ndarray) -> np.ndarray:
        """The poses (one per scan) of the scans that have a ground-truth pose, in the order of ``gt``."""
        return poses if self.gt_frames is None else poses[self.gt_frames]


def looks_planar(scans: ScanSequence, given: Trajectory | None, sample: int = 5) -> bool:
    """Planar when the source says so, or sampled scans and the given poses all lie in z = 0."""
    if scans.planar:
        return True
    idx = np.unique(np.linspace(0, len(scans) - 1, min(sample, len(scans))).astype(int))
    flat = all(np.abs(scans[int(i)].points[:, 2]).max() < 1e-6 for i in idx)
    return flat and (given is None or se3.is_planar(given.poses))


def load_inputs(
    scans_path: Path,
    scans_format: str | None,
    poses_path: Path | None,
    poses_format: str | None,
    options: ReadOptions,
    gt_path: Path | None = None,
    gt_format: str | None = None,
    relations_path: Path | None = None,
    max_diff: float = 0.01,
) -> RunInputs:
    scans = open_scans(scans_path, scans_format, options)
    log_sensor(depth_sensor(scans))
    carried = poses_path is None and scans.meta.get("poses_file")  # a layout holding its poses (HBA's pose.json)
    if carried:
        poses_path, poses_format = Path(scans.meta["poses_file"]), scans.meta.get("poses_format")
    given, fmt, full = None, None, None
    if poses_path is not None:
        full = read_trajectory(poses_path, poses_format, options)
        if carried and len(full) != len(scans):
            raise InputError(poses_path, f"{len(full)} poses for the {len(scans)} scans of "
                                         f"{scans.meta.get('scans_folder', scans.source)} (one pose per scan)")
        fmt = full.meta.get("format")
        scans, given = associate_scans(scans, full, max_diff)
        if len(given) == len(full) or given.timestamps is None or fmt == "carmen":
            full = None
    else:
        for name in CARRIED_WARM_START:
            if name in scans.trajectories:
                given, fmt = scans.trajectories[name], scans.meta.get("format")
                break
    scans.planar = looks_planar(scans, given)
    if scans.sensor is None:  # a source that cannot tell (a folder of scans in z = 0: a 2D laser): by looking
        scans.sensor = SensorKind.of_geometry(scans.planar)
    if given is not None and scans.planar:
        given.planar = True
    gt, gt_frames = None, None
    if gt_path is not None:
        gt = read_trajectory(gt_path, gt_format, options)
        gt, gt_frames = gt_for_scans(gt, scans, gt_path, max_diff)
    relations = load_relations(relations_path) if relations_path is not None else None
    return RunInputs(scans, given, fmt, poses_path, gt, relations, gt_frames, full)


def depth_sensor(scans: ScanSequence) -> dict | None:
    """What a depth-image source back-projects with: intrinsics, depth scale (units per metre), pixel stride, where
    each came from, and which were assumed (layout defaults); None for other sources."""
    meta = scans.meta
    if "intrinsics" not in meta or "depth_scale" not in meta:
        return None
    fx, fy, cx, cy = (float(v) for v in meta["intrinsics"])
    sources = {"intrinsics": str(meta.get("intrinsics_from", "")), "depth_scale": str(meta.get("depth_scale_from", ""))}
    return {"layout": meta.get("layout"), "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
            "depth_scale": float(meta["depth_scale"]), "stride": meta.get("stride"),
            "from": sources, "assumed": list(meta.get("assumed", [])),
            "smoothed": bool(meta.get("smoothed")), "image_noise": meta.get("image_noise"),
            "image_noise_line": meta.get("image_noise_line")}


def log_sensor(sensor: dict | None) -> None:
    """One line stating the depth camera in use, and one more when defaults were assumed."""
    if sensor is None:
        return
    k = sensor["intrinsics"]
    log.info("depth camera: fx %g fy %g cx %g cy %g (%s), depth scale %g units per metre (%s), pixel stride %s",
             k["fx"], k["fy"], k["cx"], k["cy"], sensor["from"]["intrinsics"], sensor["depth_scale"],
             sensor["from"]["depth_scale"], sensor["stride"])
    if sensor.get("image_noise_line"):
        log.info("%s; %s", sensor["image_noise_line"], "each pixel's depth smoothed by it over its neighbours on "
                 "the same surface (--smooth-depth)" if sensor["smoothed"] else "depth as recorded")
    if sensor["assumed"]:
        log.warning("depth camera: %s assumed from the %s layout's defaults; give --intrinsics / --depth-scale if "
                    "your camera differs", " and ".join(a.replace("_", " ") for a in sensor["assumed"]),
                    sensor["layout"])


#: the fewest scans ground truth must match to be evaluated
MIN_MATCHED = 3


def gt_for_scans(gt: Trajectory, scans: ScanSequence, path: Path, max_diff: float
                 ) -> tuple[Trajectory, np.ndarray | None]:
    """The ground-truth poses of the scans and which scans they belong to (None: all, in order).

    With stamps on both sides, each scan is paired with the nearest ground-truth stamp within ``max_diff``
    seconds, as evo associates (a 100 Hz ground truth for 10 Hz scans, a scan without ground truth nearby):
    the metrics then cover the matched scans, and how many matched is logged. Without stamps, by index."""
    if scans.timestamps is not None and gt.timestamps is not None:
        i_scan, i_gt = associate_by_time(scans.timestamps, gt.timestamps, max_diff)
        by_index = len(gt) == len(scans) and len(i_scan) < len(scans) / 2  # another time base, same frames
        if len(i_scan) >= min(MIN_MATCHED, len(scans)) and not by_index:
            order = np.argsort(i_scan)
            if len(i_scan) == len(scans):
                return gt.subset(i_gt[order]), None
            log.warning("%s: ground truth for %d of %d scans (stamps within %g s); metrics over those scans",
                        path, len(i_scan), len(scans), max_diff)
            return gt.subset(i_gt[order]), i_scan[order]
        if len(gt) != len(scans):
            span = f"{gt.timestamps[0]:.3f}-{gt.timestamps[-1]:.3f} s"
            raise InputError(path, f"no ground-truth stamp within {max_diff:g} s of the scans' stamps (ground "
                                   f"truth {span}, scans {scans.timestamps[0]:.3f}-{scans.timestamps[-1]:.3f} s; "
                                   "see --max-diff)")
    if len(gt) != len(scans):
        raise InputError(path, f"ground truth has {len(gt)} poses for {len(scans)} scans and no stamps to match "
                               "them by")
    return gt, None


def default_to_icp(cfg: RunConfig, inputs: RunInputs, asked: bool) -> bool:
    """Whether the run starts from the ``icp`` warm start instead of the default ``poses``: when there is no
    trajectory to refine, or (unless a warm start was ``asked`` for on the command line or in the config) only
    the wheel odometry a 2D laser log carries, which the icp warm start fuses with scan matching."""
    if cfg.warm_start.name != "poses":
        return False
    carried_odometry = inputs.given is not None and inputs.given_path is None and inputs.scans.planar
    return inputs.given is None or (carried_odometry and not asked)


def with_warm_start(cfg: RunConfig, inputs: RunInputs, asked_by: str | Path | None) -> RunConfig:
    """``cfg`` with the warm start this run takes (:func:`default_to_icp`); ``asked_by``: where a warm start was
    asked for (``"--warm-start"`` or the config file; None: nowhere). Asking for ``poses`` without any is an
    error naming where it was asked."""
    if asked_by is not None and cfg.warm_start.name == "poses" and inputs.given is None:
        source, what = (None, "--warm-start poses") if asked_by == "--warm-start" else (asked_by, "warm_start poses")
        raise InputError(source, f"{what} starts from a given trajectory and there is none: give --poses FILE "
                                 "(or --warm-start icp to compute one from the scans)")
    if default_to_icp(cfg, inputs, asked_by is not None):  # a validated plugin section (icp takes no options here)
        return cfg.model_copy(update={"warm_start": PluginSection(name="icp")})
    return cfg
