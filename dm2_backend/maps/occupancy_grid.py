"""2D occupancy grids: log-odds ray casting of planar scans, and the ROS ``map_server`` files (PGM + YAML).

Ray casting: each beam marks the cell of its end point occupied and the cells it crosses free. The cells
crossed are found without Bresenham: every beam is sampled at half-cell steps from the sensor up to one cell
short of its end point (so a beam never frees the cell it hits), all beams of a batch of scans at once in
numpy. As OctoMap does, a scan updates a cell at most once, and a cell that a scan both hits and crosses
counts as hit. The log-odds of a cell are ``hits * logit(P_HIT) + misses * logit(P_MISS)`` (OctoMap's sensor
model, 0.7 and 0.4), clamped to OctoMap's ``[logit(0.12), logit(0.97)]``: the sum of the per-scan updates,
so the result does not depend on the order of the scans.

Files follow ``map_server``/``map_saver``: ``map.pgm`` (binary P5, row 0 is the top of the map = largest y,
occupied 0, free 254, unknown 205) and ``map.yaml`` (``image``, ``mode``, ``resolution``, ``origin [x, y,
yaw]`` of the lower-left pixel, ``negate 0``, ``occupied_thresh 0.65``, ``free_thresh 0.196``). With ``negate
0`` a pixel value v reads as occupancy probability ``(255 - v) / 255``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

P_HIT, P_MISS = 0.7, 0.4
CLAMP = (0.12, 0.97)
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
#: map_saver's trinary pixel values
OCCUPIED, FREE, UNKNOWN = 0, 254, 205


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


@dataclass
class OccupancyGrid:
    """``log_odds[iy, ix]`` (float32) of the cell ``[x0 + ix r, x0 + (ix+1) r) x [y0 + iy r, ...)``: row 0 is
    the bottom (smallest y), as in the world; ``observed`` marks cells some beam hit or crossed."""

    log_odds: np.ndarray
    observed: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @property
    def shape(self) -> tuple[int, int]:
        return self.log_odds.shape

    def probability(self) -> np.ndarray:
        """Occupancy probability per cell, NaN where unobserved."""
        p = 1.0 / (1.0 + np.exp(-self.log_odds.astype(np.float64)))
        return np.where(self.observed, p, np.nan)

    def centers(self) -> np.ndarray:
        """World (x, y) of every cell centre, (H, W, 2)."""
        h, w = self.shape
        xs = self.origin[0] + (np.arange(w) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(h) + 0.5) * self.resolution
        X, Y = np.meshgrid(xs, ys)
        return np.stack([X, Y], -1)

    def cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(iy, ix) of world points (..., 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        ix = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return iy, ix


def grid_frame(lo: np.ndarray, hi: np.ndarray, resolution: float, max_cells: int,
               margin_cells: int = 2) -> tuple[float, tuple[float, float], tuple[int, int]]:
    """Resolution (coarsened until the grid has at most ``max_cells``), origin and (H, W) of a grid over the box
    ``[lo, hi]`` (2,) with a margin of a few cells."""
    span = np.maximum(np.asarray(hi, float) - np.asarray(lo, float), resolution)
    res = float(resolution)
    while np.prod(np.ceil(span / res) + 2 * margin_cells + 1) > max_cells:
        res *= 1.25
    origin = np.floor(np.asarray(lo, float) / res) * res - margin_cells * res
    w, h = (np.ceil((np.asarray(hi, float) - origin) / res) + margin_cells).astype(int)
    return res, (float(origin[0]), float(origin[1])), (int(h), int(w))


def ray_cast(scans: Iterable[tuple[np.ndarray, np.ndarray]], resolution: float, origin: tuple[float, float],
             shape: tuple[int, int], batch_samples: int = 1 << 22) -> OccupancyGrid:
    """The grid of ``scans``: pairs (sensor position (2,), beam end points (M, 2)) in world coordinates."""
    h, w = shape
    cells = h * w
    hits = np.zeros(cells, np.int32)
    misses = np.zeros(cells, np.int32)
    step = 0.5 * resolution
    o = np.asarray(origin, np.float64)
    pending: list[tuple[np.ndarray, np.ndarray]] = []
    size = 0

    def index(xy: np.ndarray) -> np.ndarray:
        ij = np.floor((xy - o) / resolution).astype(np.int64)
        ij[:, 0] = np.clip(ij[:, 0], 0, w - 1)
        ij[:, 1] = np.clip(ij[:, 1], 0, h - 1)
        return ij[:, 1] * w + ij[:, 0]

    def flush() -> None:
        free_keys, hit_keys = [], []
        for k, (sensor, ends) in enumerate(pending):
            d = ends - sensor
            r = np.linalg.norm(d, axis=1)
            n = np.maximum(np.floor((r - resolution) / step).astype(np.int64) + 1, 0)
            ray = np.repeat(np.arange(len(ends)), n)
            t = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) * step
            unit = d / np.maximum(r, 1e-12)[:, None]
            samples = sensor + unit[ray] * t[:, None]
            free_keys.append(index(samples) + k * cells)
            hit_keys.append(index(ends) + k * cells)
        hk = np.unique(np.concatenate(hit_keys))
        fk = np.unique(np.concatenate(free_keys))
        fk = fk[~np.isin(fk, hk, assume_unique=True)]
        np.add.at(hits, hk % cells, 1)  # a cell appears once per scan, but several scans share cells
        np.add.at(misses, fk % cells, 1)

    for sensor, ends in scans:
        ends = np.asarray(ends, np.float64).reshape(-1, 2)
        if len(ends) == 0:
            continue
        sensor = np.asarray(sensor, np.float64).reshape(2)
        pending.append((sensor, ends))
        size += int(np.linalg.norm(ends - sensor, axis=1).sum() / step) + len(ends)
        if size >= batch_samples:
            flush()
            pending, size = [], 0
    if pending:
        flush()
    lo, hi = logit(CLAMP[0]), logit(CLAMP[1])
    L = np.clip(hits * logit(P_HIT) + misses * logit(P_MISS), lo, hi).astype(np.float32)
    return OccupancyGrid(L.reshape(h, w), ((hits + misses) > 0).reshape(h, w), float(resolution),
                         (float(origin[0]), float(origin[1])))


# ---------------------------------------------------------------------------------------------- map_server files
def trinary_pixels(prob: np.ndarray) -> np.ndarray:
    """map_saver's pixels (uint8, world rows: row 0 = smallest y) of probabilities (NaN = unknown)."""
    out = np.full(prob.shape, UNKNOWN, np.uint8)
    known = np.isfinite(prob)
    out[known & (prob > OCCUPIED_THRESH)] = OCCUPIED
    out[known & (prob < FREE_THRESH)] = FREE
    return out


def scale_pixels(prob: np.ndarray) -> np.ndarray:
    """Pixels ``round(255 (1 - p))`` (negate 0: read back as p), unknown (NaN) as 205."""
    v = np.round(255.0 * (1.0 - np.clip(np.nan_to_num(prob, nan=(255 - UNKNOWN) / 255.0), 0, 1)))
    return v.astype(np.uint8)


def write_map_server(yaml_path: Path, pixels: np.ndarray, resolution: float, origin: tuple[float, float],
                     mode: str = "trinary") -> list[str]:
    """``NAME.pgm`` + ``NAME.yaml`` from pixels in world rows (row 0 = smallest y; flipped here so the
    image's first row is the top). Returns the file names written."""
    yaml_path = Path(yaml_path)
    pgm = yaml_path.with_suffix(".pgm")
    image = np.ascontiguousarray(pixels[::-1], dtype=np.uint8)
    h, w = image.shape
    with atomic_write(pgm, "wb") as fh:
        fh.write(f"P5\n# CREATOR: dm2 {resolution:.6g} m/pix\n{w} {h}\n255\n".encode("ascii"))
        fh.write(image.tobytes())
    doc = {"image": pgm.name, "mode": mode, "resolution": float(resolution),
           "origin": [float(origin[0]), float(origin[1]), 0.0], "negate": 0,
           "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH}
    with atomic_write(yaml_path) as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    return [pgm.name, yaml_path.name]


@dataclass
class MapServerMap:
    """A map read as ``map_server`` does: ``image`` (H, W) uint8 as stored (row 0 = top = largest y)."""

    image: np.ndarray
    resolution: float
    origin: tuple[float, float, float]
    negate: int
    occupied_thresh: float
    free_thresh: float
    mode: str = "trinary"

    def occupancy(self) -> np.ndarray:
        """Probability per pixel: ``(255 - v) / 255`` (``v / 255`` with negate 1)."""
        v = self.image.astype(np.float64)
        return v / 255.0 if self.negate else (255.0 - v) / 255.0

    def classes(self) -> np.ndarray:
        """map_server's trinary reading: 1 occupied, 0 free, -1 unknown."""
        p = self.occupancy()
        out = np.full(p.shape, -1, np.int8)
        out[p > self.occupied_thresh] = 1
        out[p < self.free_thresh] = 0
        return out

    def pixel(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) in the image of world points (..., 2) (origin yaw 0)."""
        xy = np.asarray(xy, dtype=np.float64)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        up = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return self.image.shape[0] - 1 - up, col


def read_pgm(path: Path) -> np.ndarray:
    """A binary (P5) or plain (P2) 8-bit PGM as (H, W) uint8."""
    data = Path(path).read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while end < len(data) and not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    magic, w, h, maxval = tokens[0], int(tokens[1]), int(tokens[2]), int(tokens[3])
    if magic not in (b"P5", b"P2") or maxval > 255:
        raise InputError(path, f"not an 8-bit PGM (magic {magic!r}, maxval {maxval})")
    if magic == b"P2":
        return np.array(data[pos:].split()[: w * h], dtype=np.uint8).reshape(h, w)
    raw = np.frombuffer(data[pos + 1 : pos + 1 + w * h], dtype=np.uint8)
    if raw.size != w * h:
        raise InputError(path, f"truncated: {raw.size} of {w * h} pixels")
    return raw.reshape(h, w).copy()


def read_map_server(yaml_path: Path) -> MapServerMap:
    """Read ``NAME.yaml`` and the image it names (relative to the YAML's folder)."""
    yaml_path = Path(yaml_path)
    doc = yaml.safe_load(yaml_path.read_text())
    missing = {"image", "resolution", "origin"} - set(doc or {})
    if missing:
        raise InputError(yaml_path, f"map YAML without {', '.join(sorted(missing))}")
    image = read_pgm(yaml_path.parent / doc["image"])
    ox, oy, yaw = (list(doc["origin"]) + [0.0, 0.0, 0.0])[:3]
    return MapServerMap(image, float(doc["resolution"]), (float(ox), float(oy), float(yaw)),
                        int(doc.get("negate", 0)), float(doc.get("occupied_thresh", OCCUPIED_THRESH)),
                        float(doc.get("free_thresh", FREE_THRESH)), str(doc.get("mode", "trinary")))
