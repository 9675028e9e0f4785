"""A depth camera's range noise, measured on its own frames, and the weights it gives the dense stage's cells.

A structured-light or time-of-flight camera's depth noise grows with the square of the range (a Kinect v1: about
1.5 mm at 1 m and 2-3 cm at 4 m, Khoshelham and Elberink 2012; Nguyen, Izadi and Lovell 2012), so one frame's
points are far from equally precise: a cell of points 3 m away sits on its plane an order of magnitude less
precisely than one at 1 m, yet counts as much. The frames measure it themselves: a flat cell's thickness (the
smallest eigenvalue of its points' covariance, along the beam for a surface seen head-on) is the range noise
there. Over the flat cells of a sample of frames, the median thickness per range decile is fitted as
``sigma^2(z) = a + b z^4`` (non-negative least squares), and each cell's points are weighed by
``sigma^2(z_ref) / sigma^2(z)`` (``z_ref`` the cells' median range, the weights clipped to
[:data:`MIN_WEIGHT`, :data:`MAX_WEIGHT`]): the dense term then sums residuals in units of their own noise, as a
least-squares estimate should. The plane term's noise scale is estimated on the weighted cells, so the weights
redistribute the term among the cells and leave its balance with the graph's factors as it was.
Why: ``docs/decisions/0017-depth-cells-weighed-by-range-noise.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from dm2_backend.kernel import planes
from dm2_backend.kernel.planes import Cells
from dm2_backend.kernel.scans import ScanSequence

#: frames sampled (evenly over the sequence) to measure the noise on
SAMPLE = 20
#: the fewest points a cell needs for its thickness to be measured, and flat cells a range decile needs
MIN_CELL_POINTS, MIN_BIN_CELLS = 20, 30
#: the weights' range, relative to a cell at the median range
MIN_WEIGHT, MAX_WEIGHT = 0.02, 10.0


@dataclass(frozen=True)
class RangeNoise:
    """``sigma^2(z) = floor + quartic z^4`` (m^2, z the range in m), fitted on ``cells`` flat cells of ``frames``
    frames; ``reference_m`` the cells' median range, where a cell keeps weight one."""

    floor: float
    quartic: float
    reference_m: float
    cells: int
    frames: int

    def sigma(self, z: np.ndarray | float) -> np.ndarray:
        """The range noise (m) at range ``z`` (m)."""
        return np.sqrt(self.floor + self.quartic * np.asarray(z, np.float64) ** 4)

    def weights(self, z: np.ndarray) -> np.ndarray:
        """Per range ``z``: ``sigma^2(z_ref) / sigma^2(z)``, clipped to [:data:`MIN_WEIGHT`, :data:`MAX_WEIGHT`]."""
        ratio = (self.sigma(self.reference_m) / np.maximum(self.sigma(z), 1e-9)) ** 2
        return np.clip(ratio, MIN_WEIGHT, MAX_WEIGHT)

    def describe(self) -> str:
        near, far = self.reference_m / 2.0, self.reference_m * 2.0
        return (f"range noise {1e3 * float(self.sigma(near)):.1f} mm at {near:.1f} m, "
                f"{1e3 * float(self.sigma(self.reference_m)):.1f} mm at {self.reference_m:.1f} m, "
                f"{1e3 * float(self.sigma(far)):.1f} mm at {far:.1f} m (measured on {self.cells} flat cells of "
                f"{self.frames} frames)")

    def summary(self) -> dict:
        return {"floor_m2": self.floor, "quartic_m2_per_m4": self.quartic, "reference_m": self.reference_m,
                "cells": self.cells, "frames": self.frames}


def measure(scans: ScanSequence, size: float, per_frame: int, sample: int = SAMPLE) -> RangeNoise | None:
    """The range noise of ``scans``' flat cells, the dense stage's (``size``, at most ``per_frame`` a frame; see
    the module docstring); None where too few flat cells or range deciles are measured to fit it."""
    frames = np.unique(np.linspace(0, len(scans) - 1, min(sample, len(scans))).astype(int))
    cells = planes.cells_from_scans(scans.subset(frames), size, per_frame, per_frame * len(frames),
                                    keep_scatter="all")
    count = cells.count.astype(np.float64)
    full = np.zeros((len(cells), 3, 3))
    iu = np.triu_indices(3)
    full[:, iu[0], iu[1]] = cells.scatter
    full[:, iu[1], iu[0]] = cells.scatter
    lam = np.linalg.eigvalsh(full / np.maximum(count, 1.0)[:, None, None])
    flat = (count >= MIN_CELL_POINTS) & (lam[:, 0] < planes.FLATNESS * lam[:, 1])
    z = np.linalg.norm(cells.mean[flat].astype(np.float64), axis=1)
    thickness = lam[flat, 0]
    if len(z) < 10 * MIN_BIN_CELLS:
        return None
    edges = np.quantile(z, np.linspace(0.0, 1.0, 11))
    bins = [(z >= a) & (z <= b) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    rows = [(np.median(z[m]), np.median(thickness[m])) for m in bins if m.sum() >= MIN_BIN_CELLS]
    if len(rows) < 3:
        return None
    zs, vs = np.array(rows).T
    (floor, quartic), _ = nnls(np.stack([np.ones_like(zs), zs**4], 1), vs)
    if floor + quartic <= 0.0:
        return None
    return RangeNoise(float(floor), float(quartic), float(np.median(z)), int(flat.sum()), len(frames))


def weighed(cells: Cells, noise: RangeNoise) -> Cells:
    """``cells`` with each one's points weighed by :meth:`RangeNoise.weights` at its mean's range (count and
    scatter scaled: a point-to-plane sum of weighted points)."""
    w = noise.weights(np.linalg.norm(cells.mean.astype(np.float64), axis=1))
    return Cells(cells.frame, (cells.count * w).astype(np.float32), cells.mean,
                 (cells.scatter * w[:, None]).astype(np.float32), cells.size)
