"""Planar laser returns that are not surfaces: an isolated long return (glass, an open door, a specular floor: one
beam reads 30-50 m between neighbours at 6-7 m that lie on one surface).

A beam is isolated when the nearest valid beam on each side lies on one surface with the other (their ranges differ
by less than :data:`SAME_SURFACE` times ``range x angle between them``: a surface seen at up to atan(5) = 79 deg
incidence) and the beam reads farther than both by more than that same tolerance: a real surface there would lie
within it of the line through its neighbours. Every threshold is the scan's own range and angular step; a narrow
gap through which the laser sees far (one beam wide) is dropped with the spurious returns, which costs one point.
"""

from __future__ import annotations

import numpy as np

#: two beams lie on one surface when their ranges differ by less than this many times ``range x angle between
#: them`` (a surface seen at up to atan(5) = 79 deg incidence)
SAME_SURFACE = 5.0


def _nearest_valid(valid: np.ndarray, side: int) -> np.ndarray:
    """Index of the nearest valid beam before (``side`` -1) or after (+1) each beam; -1 where there is none."""
    n = len(valid)
    idx = np.where(valid, np.arange(n), -1 if side < 0 else n)
    if side < 0:
        prev = np.maximum.accumulate(np.concatenate([[-1], idx[:-1]]))
        return prev
    nxt = np.minimum.accumulate(np.concatenate([idx[1:], [n]])[::-1])[::-1]
    return np.where(nxt >= n, -1, nxt)


def isolated_long_returns(ranges: np.ndarray, valid: np.ndarray, step: float) -> np.ndarray:
    """Mask of the valid beams of one planar scan (``ranges`` in beam order, ``step`` rad between beams) that read
    beyond both their nearest valid neighbours while those two lie on one surface (see the module)."""
    r = np.asarray(ranges, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    left, right = _nearest_valid(valid, -1), _nearest_valid(valid, +1)
    has = valid & (left >= 0) & (right >= 0)
    i = np.flatnonzero(has)
    rl, rr, ri = r[left[i]], r[right[i]], r[i]
    near = np.minimum(rl, rr)
    tolerance = SAME_SURFACE * abs(step) * (right[i] - left[i]) * near
    isolated = (np.abs(rl - rr) < tolerance) & (ri > np.maximum(rl, rr) + tolerance)
    out = np.zeros(len(r), dtype=bool)
    out[i[isolated]] = True
    return out
