"""The preparation steps (frames -> warm start -> topology -> pairwise), each cached on disk.

Each step's cache key hashes the key of the step before it, its own plugin name, options and code, and the
first step's the input files and read options (:mod:`dm2_backend.prepare.cache_keys`), so a second run on the
same data (``dm2 refine`` again, or ``dm2 baseline``) loads the results instead of recomputing them. Entries
are folders of ``.npy`` arrays (:mod:`dm2_backend.prepare.store`); the frames' points and the pairwise
relatives are memory-mapped, also right after a step computed them, so the processes of a distributed run
share their pages.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dm2_backend.algorithms.common import path_length, repeatable_registration
from dm2_backend.config.schema import ConfigError, PluginSection, RunConfig, check_plugin_options
from dm2_backend.kernel.prepared import Frames, Pairwise, Topology
from dm2_backend.kernel.scans import DEPTH_CAMERA, ScanSequence
from dm2_backend.kernel.trajectory import Trajectory
from dm2_backend.plugins.registry import load as load_plugin
from dm2_backend.prepare import store
from dm2_backend.prepare.cache_keys import code_fingerprint, source_key, step_key
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.stage_log import StageLog

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prepared:
    frames: Frames
    warm_start: np.ndarray
    topology: Topology
    pairwise: Pairwise
    #: each step's seconds and the peak memory when it ended
    stages: StageLog = field(default_factory=StageLog)
    cached: dict[str, bool] = field(default_factory=dict)
    #: step -> name of its cache entry (see :func:`load_prepared`)
    keys: dict[str, str] = field(default_factory=dict)
    #: config section -> its plugin as run, ``auto`` resolved (the caller's config is left as given)
    resolved: dict[str, PluginSection] = field(default_factory=dict)
    #: what the warm-start plugin reported about its run (its ``report`` attribute; e.g. the ``icp`` warm
    #: start's per-step sources), None when it reports nothing
    warm_report: dict | None = None

    @property
    def initial(self) -> np.ndarray:
        """Where the optimiser and the baselines start: the loop-closed poses of the place recognition when
        it made them, else the warm start."""
        return starting_poses(self.topology, self.warm_start)


def starting_poses(topology: Topology, warm: np.ndarray) -> np.ndarray:
    """The loop-closed poses of the place recognition when it made them, else the warm start."""
    return topology.poses if topology.poses is not None else warm


#: a ground vehicle's sensor stays within this angle of its mean up direction (road grades and camber are a few
#: degrees); a hand-held, backpack or drone sensor tilts further (the real LiDAR keyframes: 95th percentile 31°)
GROUND_MAX_TILT_DEG = 15.0
#: ... and climbs less than this fraction of its path (ramps and hills)
GROUND_MAX_CLIMB = 0.1


def moves_like_a_ground_vehicle(poses: np.ndarray, planar: bool) -> bool:
    """Whether the sensor keeps one axis up and its height along it (roll/pitch spread and vertical travel of
    the warm start), as bird's-eye loop closure (``loops``) assumes."""
    if planar or len(poses) < 2:
        return True
    up = poses[:, :3, 2]  # the sensor's z axis in the world
    mean = up.mean(0)
    mean /= max(np.linalg.norm(mean), 1e-12)
    tilt = np.degrees(np.arccos(np.clip(up @ mean, -1.0, 1.0)))
    height = poses[:, :3, 3] @ mean
    path = float(path_length(poses)[-1])
    return bool(np.percentile(tilt, 95) <= GROUND_MAX_TILT_DEG and np.ptp(height) <= GROUND_MAX_CLIMB * max(path, 1e-9))


def resolve_auto(section: PluginSection, camera: bool, poses: np.ndarray | None = None,
                 planar: bool = False) -> PluginSection:
    """Place recognition ``auto``: ``loops`` (loop closure under large drift, matching bird's-eye views) for
    laser scanners that move like a ground vehicle; ``loops3d`` (6-DoF loop closure) for depth-camera sequences
    (a hand-held camera's frame has no vertical axis to look down) and for scanners that tilt or climb (hand-held,
    backpack, drone; see :func:`moves_like_a_ground_vehicle` on the warm start ``poses``)."""
    if section.name != "auto":
        return section
    ground = poses is None or moves_like_a_ground_vehicle(poses, planar)
    resolved = PluginSection(name="loops3d" if camera or not ground else "loops", options=dict(section.options))
    try:  # the options against the plugin now named, as a named one is checked at load
        check_plugin_options("place_recognition", "dm2.place_recognition", resolved.name, resolved.options)
    except ConfigError as exc:
        raise InputError(None, f"{exc} (place recognition auto resolved to {resolved.name})") from None
    return resolved


def default_cache_dir() -> Path:
    return Path(os.environ.get("DM2_CACHE_DIR", Path.home() / ".cache" / "dm2"))


def _code(group: str, section: PluginSection) -> str:
    """The code fingerprint of the plugin a section names (its module and the dm2 modules it uses)."""
    return code_fingerprint(load_plugin(group, section.name))


def _plugin(group: str, section: PluginSection, progress: bool = True):
    cls = load_plugin(group, section.name)
    options = dict(section.options)
    if not progress and "progress" in getattr(cls, "__dataclass_fields__", {}):
        options.setdefault("progress", False)  # --quiet silences the plugins' bars too
    try:
        return cls(**options)
    except TypeError as exc:
        raise InputError(None, f"{group} plugin {section.name!r}: {exc}") from exc


class _Cache:
    """Cache entries (``store`` folders) under ``root``; with no root nothing is cached."""

    def __init__(self, root: Path | None) -> None:
        self.root = root

    def get(self, name: str) -> tuple[dict[str, np.ndarray], dict] | None:
        return store.get(self.root, name)

    def put(self, name: str, arrays: dict, meta: dict | None = None) -> tuple[dict[str, np.ndarray], dict] | None:
        """Store the entry and return it as read back (memory-mapped), or None without a cache."""
        if self.root is None:
            return None
        store.put(self.root, name, arrays, meta)
        return self.get(name)


def load_prepared(cache_dir: Path, keys: dict[str, str]) -> Prepared:
    """The results of a finished :func:`prepare` from the cache, by the entry names in ``Prepared.keys``
    (how the processes of a distributed run load what the first one prepared)."""
    hits = {step: store.get(cache_dir, name) for step, name in keys.items()}
    missing = [keys[step] for step, hit in hits.items() if hit is None]
    if missing:
        raise FileNotFoundError(f"preparation cache {cache_dir} lacks {', '.join(missing)}")
    frames = store.frames_from(*hits["frames"], cache_dir / keys["frames"])
    return Prepared(frames, hits["warm_start"][0]["poses"], store.topology_from(hits["place_recognition"]),
                    store.pairwise_from(hits["registration"]), cached=dict.fromkeys(keys, True), keys=dict(keys),
                    warm_report=hits["warm_start"][1].get("report"))


@dataclass
class Step:
    """One cached preparation step: its name in the run's records, the name of its cache entry, how to compute
    its result, how to store it (returning the entry as read back, or None without a cache) and how to read a
    stored entry."""

    name: str
    entry: str
    compute: Callable[[], Any]
    save: Callable[[_Cache, str, Any], tuple | None]
    read: Callable[[tuple], Any]


@dataclass
class _Record:
    """What the steps of one preparation leave besides their results."""

    stages: StageLog = field(default_factory=StageLog)
    cached: dict[str, bool] = field(default_factory=dict)
    keys: dict[str, str] = field(default_factory=dict)

    def run(self, step: Step, cache: _Cache) -> Any:
        """The step's result from the cache, or computed and stored; timed and recorded."""
        self.keys[step.name] = step.entry
        with self.stages.stage(step.name):
            hit = cache.get(step.entry)
            self.cached[step.name] = hit is not None
            if hit is None:
                value = step.compute()
                hit = step.save(cache, step.entry, value)
            return step.read(hit) if hit is not None else value


def _save_frames(cache: _Cache, name: str, frames: Frames) -> tuple | None:
    if cache.root is None:
        return None
    store.put_frames(cache.root, name, frames)
    return cache.get(name)  # from here on the frames are memory-mapped; the copy in memory is dropped


def _save_topology(cache: _Cache, name: str, topo: Topology) -> tuple | None:
    arrays = {"groups": topo.groups, "edges": topo.edges}
    if topo.poses is not None:
        arrays["poses"] = topo.poses
    return cache.put(name, arrays, {"edge_kind": topo.edge_kind, "log": topo.log, "loop_closed": topo.loop_closed,
                                    "closures": topo.closures, "repaired_steps": list(topo.repaired_steps)})


def _save_pairwise(cache: _Cache, name: str, pair: Pairwise) -> tuple | None:
    arrays = {"relative": pair.relative, "valid": pair.valid, "fitness": pair.fitness, "rmse": pair.rmse}
    if pair.hessian is not None:
        arrays.update(hessian=pair.hessian, plane_rmse=pair.plane_rmse)
    return cache.put(name, arrays, {"reason": {f"{i},{j}": r for (i, j), r in pair.reason.items()}})


def prepare(
    scans: ScanSequence,
    given: Trajectory | None,
    cfg: RunConfig,
    cache_dir: Path | None,
    progress: bool = True,
) -> Prepared:
    """Run (or load from ``cache_dir``) the preparation steps configured in ``cfg``, each a :class:`Step` whose
    cache key hashes the key of the step before it."""
    cache, record = _Cache(cache_dir), _Record()
    fcfg = cfg.frames
    from dm2_backend.prepare import frames as frames_module

    def load() -> Frames:
        from dm2_backend.prepare.frames import load_frames  # open3d: not imported by ranks that only read

        return load_frames(scans, fcfg.max_points, fcfg.voxel, cfg.seed, progress)

    k_frames = step_key(source_key(scans), fcfg.model_dump(), cfg.seed, scans.planar, code_fingerprint(frames_module))
    entry = f"frames-{k_frames}"
    frames = record.run(Step("frames", entry, load, _save_frames,
                             lambda hit: store.frames_from(*hit, cache.root / entry if cache.root else None)), cache)

    with repeatable_registration():  # the same poses every run
        ws = cfg.warm_start
        given_hash = hashlib.sha1(given.poses.tobytes()).hexdigest() if given is not None else ""
        k_ws = step_key(k_frames, ws.model_dump(), given_hash, _code("dm2.warm_start", ws))

        def warm_start() -> tuple[np.ndarray, dict | None]:
            plugin = _plugin("dm2.warm_start", ws, progress)
            poses = plugin.run(frames, given)
            return poses, getattr(plugin, "report", None)

        def save_warm(c: _Cache, name: str, value: tuple[np.ndarray, dict | None]) -> tuple | None:
            c.put(name, {"poses": value[0]}, {"report": value[1]} if value[1] else None)
            return None  # the poses in memory are used (as read back they would be the same)

        warm, warm_report = record.run(Step("warm_start", f"warm-{k_ws}", warm_start, save_warm,
                                            lambda hit: (hit[0]["poses"], hit[1].get("report"))), cache)
        if warm_report and warm_report.get("summary"):
            log.info("%s", warm_report["summary"])

        pr = resolve_auto(cfg.place_recognition, scans.sensor == DEPTH_CAMERA, warm, frames.planar)
        k_pr = step_key(k_ws, pr.model_dump(), _code("dm2.place_recognition", pr))
        topo = record.run(Step("place_recognition", f"topology-{k_pr}",
                               lambda: _plugin("dm2.place_recognition", pr, progress).run(frames, warm),
                               _save_topology, store.topology_from), cache)

        reg = cfg.registration
        k_reg = step_key(k_pr, reg.model_dump(), _code("dm2.registration", reg))
        pair = record.run(Step("registration", f"pairwise-{k_reg}",
                               lambda: _plugin("dm2.registration", reg, progress).run(
                                   frames, starting_poses(topo, warm), topo),
                               _save_pairwise, store.pairwise_from), cache)
    resolved = {"warm_start": ws, "place_recognition": pr, "registration": reg}
    return Prepared(frames, warm, topo, pair, record.stages, record.cached, record.keys, resolved, warm_report)
