"""A depth camera's noise, measured on its own images, and the edge-preserving smoothing it sets.

Structured-light and stereo cameras measure depth through disparity in whole sub-pixel steps: a Kinect v1 reports
depth in steps of about z^2 / 350 m (3 mm at 1 m, 4.6 cm at 4 m; RedKitchen's images: 2 mm at 0.9 m, 31 mm at 3 m),
with noise of a similar size on top. A wall seen from afar becomes a staircase locked to the camera, and registering
two such frames pulls their relative pose towards the one that keeps the staircases aligned: standing still.
:func:`smooth` (``--smooth-depth``; off by default: docs/decisions/0022-depth-smoothing-available-off.md) replaces
each kept pixel's depth by the harmonic mean of its image neighbours' depths (the mean of their inverse depths,
weighed by a Gaussian window of :data:`SPATIAL_SIGMA` pixels) over those that lie within :data:`TOLERANCE` noise
steps of it: a bilateral filter's range test, as KinectFusion's front end smooths its depth. Inverse depth is affine
in the pixel coordinates on a plane, so a plane keeps its place, and a depth edge larger than the tolerance stays.

The noise is measured per range decile on a sample of the sequence's images (:func:`measure`):

- the step: the median gap between consecutive distinct depth values (the depth unit where depth is not quantised;
  a bin holding fewer than two distinct values is left out);
- the scatter: the robust spread of the second difference along image rows (sqrt(6) sigma for independent noise).

The range tolerance at depth z is ``TOLERANCE x sqrt(step(z)^2 + sigma(z)^2)``, interpolated between the deciles.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

#: pixels: the spatial window's standard deviation and half width
SPATIAL_SIGMA, HALF_WIDTH = 1.5, 3
#: a neighbour joins the mean when its depth lies within this many noise steps of the pixel's
TOLERANCE = 3.0
#: range bins the noise is measured in, and the fewest valid pixels a measurement needs
BINS, MIN_PIXELS = 10, 10_000


@dataclass(frozen=True)
class DepthImageNoise:
    """Per range bin (``ranges_m``, the bins' median depths): the depth step and the scatter (m), measured on
    ``images`` images."""

    ranges_m: tuple[float, ...]
    steps_m: tuple[float, ...]
    sigmas_m: tuple[float, ...]
    images: int

    def tolerance(self, z: np.ndarray) -> np.ndarray:
        """The largest depth difference (m) at which a neighbour of a pixel at depth ``z`` (m) is the same surface."""
        step = np.interp(z, self.ranges_m, self.steps_m)
        sigma = np.interp(z, self.ranges_m, self.sigmas_m)
        return TOLERANCE * np.sqrt(step**2 + sigma**2)

    def summary(self) -> dict[str, object]:
        """The measurement and the smoothing's constants, as JSON-ready values (``report.json``, the cache key)."""
        return {"ranges_m": list(self.ranges_m), "steps_m": list(self.steps_m), "sigmas_m": list(self.sigmas_m),
                "images": self.images, "tolerance_steps": TOLERANCE, "spatial_sigma_px": SPATIAL_SIGMA,
                "half_width_px": HALF_WIDTH}

    def describe(self) -> str:
        """One line: the step and the scatter at the nearest, the middle and the farthest bin."""
        picks = sorted({0, len(self.ranges_m) // 2, len(self.ranges_m) - 1})
        parts = [f"step {1e3 * self.steps_m[i]:.1f} mm, scatter {1e3 * self.sigmas_m[i]:.1f} mm at "
                 f"{self.ranges_m[i]:.1f} m" for i in picks]
        return f"depth noise measured on {self.images} images: " + "; ".join(parts)


def measure(depths: Iterable[np.ndarray], scale: float) -> DepthImageNoise | None:
    """The noise of depth images ``depths`` (raw units, ``scale`` units per metre; a float image's steps have no
    floor); None when they hold fewer than :data:`MIN_PIXELS` valid pixels with valid row neighbours."""
    zs, second, count, unit = [], [], 0, 0.0
    for depth in depths:
        depth = np.asarray(depth)
        unit = 1.0 / scale if np.issubdtype(depth.dtype, np.integer) else 0.0
        z = _metres(depth, scale)
        d2 = z[:, :-2] - 2.0 * z[:, 1:-1] + z[:, 2:]
        ok = np.isfinite(d2)
        if ok.any():
            zs.append(z[:, 1:-1][ok])
            second.append(d2[ok])
            count += 1
    if not zs or sum(len(z) for z in zs) < MIN_PIXELS:
        return None
    z, d2 = np.concatenate(zs), np.abs(np.concatenate(second))
    edges = np.quantile(z, np.linspace(0.0, 1.0, BINS + 1))
    bins = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, BINS - 1)
    ranges, steps, sigmas = [], [], []
    for b in range(BINS):
        inside = bins == b
        gaps = np.diff(np.unique(z[inside]))
        if inside.sum() < MIN_PIXELS // BINS or len(gaps) == 0:
            continue
        ranges.append(float(np.median(z[inside])))
        steps.append(float(max(np.median(gaps), unit)))
        sigmas.append(float(1.4826 * np.median(d2[inside]) / np.sqrt(6.0)))
    if not ranges:
        return None
    return DepthImageNoise(tuple(ranges), tuple(steps), tuple(sigmas), count)


def smooth(depth: np.ndarray, scale: float, noise: DepthImageNoise, stride: int = 1) -> np.ndarray:
    """Depth (m, float32; 0 where invalid) at every ``stride``-th pixel of ``depth`` (raw units), each the harmonic
    mean of its neighbours' depths on the same surface (the module's rule)."""
    z = _metres(depth, scale)
    z[~np.isfinite(z)] = np.inf
    h, (rows, cols) = HALF_WIDTH, z.shape
    centre = z[::stride, ::stride]
    valid = np.isfinite(centre)
    tolerance = np.where(valid, noise.tolerance(np.where(valid, centre, 0.0)), 0.0)
    padded = np.pad(z, h, constant_values=np.inf)
    inverse = np.zeros(centre.shape)
    weight = np.zeros(centre.shape)
    with np.errstate(invalid="ignore"):  # inf - inf where neither pixel is valid: no weight
        for dy in range(-h, h + 1):
            for dx in range(-h, h + 1):
                near = padded[h + dy:h + dy + rows:stride, h + dx:h + dx + cols:stride]
                w = np.exp(-(dx * dx + dy * dy) / (2.0 * SPATIAL_SIGMA**2)) * (np.abs(near - centre) <= tolerance)
                inverse += w / near
                weight += w
    out = np.zeros(centre.shape, np.float32)
    out[valid] = weight[valid] / inverse[valid]
    return out


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """Where a depth image holds a depth: not 0, not 65535 in 16 bits, finite."""
    d = np.asarray(depth)
    return (d > 0) & (d < 65535) if d.dtype == np.uint16 else (d > 0) & np.isfinite(d)


def _metres(depth: np.ndarray, scale: float) -> np.ndarray:
    """Depth in metres, NaN where invalid (:func:`valid_depth`)."""
    d = np.asarray(depth)
    return np.where(valid_depth(d), d.astype(np.float64) / scale, np.nan)
