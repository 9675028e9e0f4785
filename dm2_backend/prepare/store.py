"""The preparation cache on disk: each entry a folder of ``.npy`` arrays plus ``meta.json``, written atomically.

The large arrays (the frames' points, the points sampled for the optimiser, the pairwise relatives) are opened
memory-mapped, so several processes on one machine share the same pages and a sequence larger than RAM is
paged in as the groups in flight need it. The frames' points are mapped read-only (a write raises); the
other two copy-on-write, so a tensor made from them without a copy stays writable (a written page becomes
private). The small per-frame arrays are read into memory.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from dm2_backend.kernel.prepared import Frames, Pairwise, ScanScale, Topology
from dm2_backend.runtime.atomic import atomic_path
from dm2_backend.runtime.errors import InputError

log = logging.getLogger(__name__)

#: arrays opened memory-mapped, with their numpy mmap mode; the others are read into memory
MAPPED = {"points": "r", "samples": "c", "relative": "c"}


#: the file that makes a folder a dm2 cache: ``dm2 cache clear`` removes entries only where it is
CACHE_MARKER = ".dm2-cache"


def is_cache(root: Path) -> bool:
    """Whether ``root`` is a folder dm2 made its cache (it holds :data:`CACHE_MARKER`, a plain file)."""
    marker = root / CACHE_MARKER
    return marker.is_file() and not marker.is_symlink()


def is_entry(folder: Path) -> bool:
    """Whether ``folder`` is a cache entry as :func:`put` writes it: a real folder with its ``meta.json``
    listing its arrays."""
    meta = folder / "meta.json"
    if folder.is_symlink() or not folder.is_dir() or meta.is_symlink() or not meta.is_file():
        return False
    try:
        return meta.stat().st_size < 1 << 20 and "arrays" in json.loads(meta.read_text())
    except (OSError, ValueError, TypeError):
        return False


def _mark(root: Path) -> None:
    root.mkdir(parents=True, exist_ok=True)
    if not (root / CACHE_MARKER).exists():
        try:
            with open(root / CACHE_MARKER, "x") as fh:
                fh.write("dm2 preparation cache: `dm2 cache clear` removes the entries dm2 wrote here\n")
        except FileExistsError:
            pass


def put(root: Path, name: str, arrays: dict[str, np.ndarray | list[np.ndarray]], meta: dict | None = None) -> None:
    """Write the entry ``root/name`` (a folder); it appears complete or not at all. A list of arrays is
    written concatenated along the first axis, one piece at a time (no concatenated copy in memory). The
    folder is marked as a dm2 cache (:data:`CACHE_MARKER`)."""
    _mark(root)
    if (root / name).is_dir():  # another process (a rank of the same run) wrote it meanwhile
        return
    try:
        with atomic_path(root / name) as tmp:
            tmp.mkdir()
            for key, value in arrays.items():
                if isinstance(value, list):
                    _save_pieces(tmp / f"{key}.npy", value)
                else:
                    np.save(tmp / f"{key}.npy", np.ascontiguousarray(value), allow_pickle=False)
            (tmp / "meta.json").write_text(json.dumps({**(meta or {}), "arrays": sorted(arrays)}, default=float))
    except InputError:
        if not (root / name).is_dir():  # not the race with another rank writing the same entry
            raise


def _save_pieces(path: Path, pieces: list[np.ndarray]) -> None:
    rows = sum(len(p) for p in pieces)
    if rows == 0:
        np.save(path, np.concatenate(pieces) if pieces else np.zeros((0, 3), np.float32), allow_pickle=False)
        return
    dtype = pieces[0].dtype
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
              "shape": (rows, *pieces[0].shape[1:])}
    with open(path, "wb") as fh:  # written, not memory-mapped: a full disk is an error here, not a bus error
        np.lib.format.write_array_header_1_0(fh, header)
        for p in pieces:
            fh.write(np.ascontiguousarray(p, dtype=dtype).tobytes())


def _load(path: Path) -> np.ndarray:
    if path.stem in MAPPED:
        try:
            return np.asarray(np.load(path, mmap_mode=MAPPED[path.stem], allow_pickle=False))  # a plain view
        except ValueError:  # an empty array cannot be mapped
            pass
    return np.load(path, allow_pickle=False)


def get(root: Path | None, name: str) -> tuple[dict[str, np.ndarray], dict] | None:
    """The arrays and metadata of entry ``name``, or None when it is not in the cache. A damaged entry
    (truncated or unreadable arrays, broken metadata, a missing array) is reported in one line, removed and
    treated as missing, so the step is computed again."""
    folder = root / name if root is not None else None
    if folder is None or not (folder / "meta.json").is_file():
        return None
    with contextlib.suppress(OSError):  # a cache of an earlier dm2, read only: marked as it is used
        _mark(root)
    try:
        meta = json.loads((folder / "meta.json").read_text())
        arrays = {p.stem: _load(p) for p in folder.glob("*.npy")}
        missing = [key for key in meta.get("arrays", arrays) if key not in arrays]
        if missing:
            raise ValueError(f"missing {', '.join(missing)}")
    except (OSError, ValueError, EOFError) as exc:  # json.JSONDecodeError is a ValueError
        log.warning("cache entry %s is damaged (%s): computing it again", folder, str(exc).splitlines()[0][:120])
        shutil.rmtree(folder, ignore_errors=True)
        return None
    return arrays, meta


def put_frames(root: Path, name: str, frames: Frames) -> None:
    """Frames as one (sum M_i, 3) float32 array of all points and the (N + 1,) offsets of each frame."""
    offsets = np.zeros(len(frames) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(p) for p in frames.points])
    arrays = {"points": [np.asarray(p, dtype=np.float32) for p in frames.points], "offsets": offsets}
    if frames.timestamps is not None:
        arrays["timestamps"] = frames.timestamps
    put(root, name, arrays, {"planar": bool(frames.planar), "scale": frames.scale.to_dict()})


def frames_from(arrays: dict[str, np.ndarray], meta: dict, folder: Path | None = None) -> Frames:
    """Frames whose points are views of the (memory-mapped) concatenated array: no copy; ``folder``: the entry
    they were read from (tasks on other processes read them there)."""
    pts, offsets = arrays["points"], arrays["offsets"]
    points = [pts[offsets[i] : offsets[i + 1]] for i in range(len(offsets) - 1)]
    return Frames(points=points, timestamps=arrays.get("timestamps"), planar=bool(meta["planar"]),
                  scale=ScanScale.from_dict(meta["scale"]), stored=None if folder is None else folder.resolve())


def topology_from(hit: tuple[dict, dict]) -> Topology:
    arrays, meta = hit
    return Topology(arrays["groups"], arrays["edges"], meta["edge_kind"], meta["log"], poses=arrays.get("poses"),
                    loop_closed=bool(meta.get("loop_closed", False)), closures=int(meta.get("closures", 0)),
                    repaired_steps=tuple(int(k) for k in meta.get("repaired_steps", ())))


def pairwise_from(hit: tuple[dict, dict]) -> Pairwise:
    arrays, meta = hit
    reasons = {tuple(map(int, k.split(","))): v for k, v in meta["reason"].items()}
    return Pairwise(arrays["relative"], arrays["valid"], arrays["fitness"], arrays["rmse"], reasons,
                    arrays.get("hessian"), arrays.get("plane_rmse"))
