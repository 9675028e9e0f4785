"""Run the preparation steps (frames -> warm start -> topology -> pairwise), each cached on disk.

Each step's cache key hashes its inputs' keys and its own plugin name and options, so a second run on the
same data (``dm2 refine`` again, or ``dm2 baseline``) loads the results instead of recomputing them.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend import __version__
from dm2_backend.atomic import atomic_write
from dm2_backend.errors import InputError
from dm2_backend.plugins.registry import load as load_plugin
from dm2_backend.prepare.frames import load_frames
from dm2_backend.prepare.types import Frames, Pairwise, Topology
from dm2_backend.scans import ScanSequence
from dm2_backend.trajectory import Trajectory


@dataclass
class Prepared:
    frames: Frames
    warm_start: np.ndarray
    topology: Topology
    pairwise: Pairwise
    timings: dict[str, float] = field(default_factory=dict)
    cached: dict[str, bool] = field(default_factory=dict)


def default_cache_dir() -> Path:
    return Path(os.environ.get("DM2_CACHE_DIR", Path.home() / ".cache" / "dm2"))


def _key(*parts) -> str:
    """Cache key of a step; includes the dm2 version so an upgrade never reuses results of older code."""
    blob = json.dumps([__version__, *parts], sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:16]


def _source_key(scans: ScanSequence) -> list:
    src = Path(scans.source) if scans.source else None
    stat = src.stat() if src is not None and src.exists() else None
    return [str(src.resolve()) if src else "", stat.st_mtime_ns if stat else 0, len(scans)]


def _plugin(group: str, section: dict, progress: bool = True):
    cls = load_plugin(group, section["name"])
    options = dict(section.get("options") or {})
    if not progress and "progress" in getattr(cls, "__dataclass_fields__", {}):
        options.setdefault("progress", False)  # --quiet silences the plugins' bars too
    try:
        return cls(**options)
    except TypeError as exc:
        raise InputError(None, f"{group} plugin {section['name']!r}: {exc}") from exc


class _Cache:
    def __init__(self, root: Path | None) -> None:
        self.root = root

    def get(self, name: str) -> dict | None:
        if self.root is None or not (self.root / name).exists():
            return None
        with np.load(self.root / name, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}

    def put(self, name: str, **arrays) -> None:
        if self.root is None:
            return
        with atomic_write(self.root / name, "wb") as fh:
            np.savez(fh, **arrays)


def prepare(
    scans: ScanSequence,
    given: Trajectory | None,
    cfg: dict,
    cache_dir: Path | None,
    progress: bool = True,
) -> Prepared:
    """Run (or load from ``cache_dir``) the three preparation steps configured in ``cfg``."""
    cache = _Cache(cache_dir)
    timings: dict[str, float] = {}
    cached: dict[str, bool] = {}
    fcfg = cfg["frames"]
    k_frames = _key(_source_key(scans), fcfg, cfg["seed"], scans.planar)
    t = time.perf_counter()
    hit = cache.get(f"frames-{k_frames}.npz")
    if hit is not None:
        counts = hit["counts"]
        points = np.split(hit["points"], np.cumsum(counts)[:-1])
        scale = json.loads(str(hit["scale"]))
        stamps = hit["timestamps"] if hit["timestamps"].size else None
        frames = Frames(points=list(points), timestamps=stamps, planar=bool(hit["planar"]), scale=scale)
    else:
        frames = load_frames(scans, fcfg["max_points"], fcfg.get("voxel"), cfg["seed"], progress)
        cache.put(
            f"frames-{k_frames}.npz", points=np.concatenate(frames.points),
            counts=np.array([len(p) for p in frames.points]), scale=json.dumps(frames.scale),
            timestamps=frames.timestamps if frames.timestamps is not None else np.zeros(0),
            planar=frames.planar,
        )
    timings["frames"], cached["frames"] = time.perf_counter() - t, hit is not None

    ws = cfg["warm_start"]
    given_hash = hashlib.sha1(given.poses.tobytes()).hexdigest() if given is not None else ""
    k_ws = _key(k_frames, ws, given_hash)
    t = time.perf_counter()
    hit = cache.get(f"warm-{k_ws}.npz")
    if hit is not None:
        warm = hit["poses"]
    else:
        warm = _plugin("dm2.warm_start", ws, progress).run(frames, given)
        cache.put(f"warm-{k_ws}.npz", poses=warm)
    timings["warm_start"], cached["warm_start"] = time.perf_counter() - t, hit is not None

    pr = cfg["place_recognition"]
    k_pr = _key(k_ws, pr)
    t = time.perf_counter()
    hit = cache.get(f"topology-{k_pr}.npz")
    if hit is not None:
        topo = Topology(hit["groups"], hit["edges"], json.loads(str(hit["edge_kind"])), json.loads(str(hit["log"])))
    else:
        topo = _plugin("dm2.place_recognition", pr, progress).run(frames, warm)
        cache.put(
            f"topology-{k_pr}.npz", groups=topo.groups, edges=topo.edges,
            edge_kind=json.dumps(topo.edge_kind), log=json.dumps(topo.log, default=float),
        )
    timings["place_recognition"], cached["place_recognition"] = time.perf_counter() - t, hit is not None

    reg = cfg["registration"]
    k_reg = _key(k_pr, reg)
    t = time.perf_counter()
    hit = cache.get(f"pairwise-{k_reg}.npz")
    if hit is not None:
        reasons = {tuple(map(int, k.split(","))): v for k, v in json.loads(str(hit["reason"])).items()}
        pair = Pairwise(hit["relative"], hit["valid"], hit["fitness"], hit["rmse"], reasons)
    else:
        pair = _plugin("dm2.registration", reg, progress).run(frames, warm, topo)
        cache.put(
            f"pairwise-{k_reg}.npz", relative=pair.relative, valid=pair.valid, fitness=pair.fitness,
            rmse=pair.rmse, reason=json.dumps({f"{i},{j}": r for (i, j), r in pair.reason.items()}),
        )
    timings["registration"], cached["registration"] = time.perf_counter() - t, hit is not None
    return Prepared(frames, warm, topo, pair, timings, cached)
