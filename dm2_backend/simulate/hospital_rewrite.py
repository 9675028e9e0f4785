"""A real CARMEN log rewritten as the hospital's scanner would have written it (issue 27's hard cases): ROBOTLASER1
messages only, with the traits of :class:`~dm2_backend.simulate.hospital.HospitalTraits` applied to the log's own
scans: interlaced quarter scans (each scan resampled at its quarter's angles), max-range codes, isolated long
returns and pauses (the stamps of the log and of its ``.relations`` moved on together). The laser's mount is not
applied: the source's scans were taken at its laser pose, and its relations are between those poses.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from dm2_backend.formats.carmen import load, max_range, robotlaser1_line
from dm2_backend.formats.carmen_parser import SCAN_ORDER
from dm2_backend.kernel.planar_returns import SAME_SURFACE
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.simulate.hospital import MAX_RANGE_CODE, HospitalTraits, pauses, returns_with_traits


def resample(r: np.ndarray, fraction: float, resolution: float) -> np.ndarray:
    """Ranges at the angles ``fraction`` (0 <= f < 1) of a beam step (``resolution``, rad) past each of ``r``'s
    beams: linear between two valid beams on one surface (:data:`~dm2_backend.kernel.planar_returns.SAME_SURFACE`), else
    the nearer beam's reading, the shorter at exactly half a step (never a phantom point between a wall and what is
    behind it); the last beam has no right neighbour and returns nothing (inf) unless ``fraction`` is 0.
    ``r``: invalid readings are inf."""
    if fraction == 0.0:
        return r.copy()
    left, right = r, np.append(r[1:], np.inf)
    nearer = left if fraction < 0.5 else right
    if fraction == 0.5:
        nearer = np.minimum(left, right)
    with np.errstate(invalid="ignore"):
        same = np.isfinite(left) & np.isfinite(right) & (np.abs(left - right) < SAME_SURFACE * resolution
                                                           * np.minimum(left, right))
        return np.where(same, (1.0 - fraction) * left + fraction * right, nearer)


def _quarter(k: int, traits: HospitalTraits) -> int:
    return k % 4 if traits.interlaced else 0


def rewrite_lines(path: str | Path, traits: HospitalTraits, seed: int = 0, first: int = 0,
                  count: int | None = None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The ROBOTLASER1 lines of the log's scan messages ``first .. first + count``, the source stamps of those scans
    and the pause each adds before the next (s, per scan: the shift of every later stamp is the sum before it)."""
    log = load(path)
    kind = next(k for k in SCAN_ORDER if k in log.messages)
    msgs = log.messages[kind][first: None if count is None else first + count]
    no_return = max_range(log, kind) or MAX_RANGE_CODE
    rng = np.random.default_rng([seed, 27, 1])
    at, length = pauses(len(msgs), traits.gaps, rng)
    added = np.zeros(len(msgs))
    added[at] = length
    shift = np.concatenate([[0.0], np.cumsum(added)[:-1]])
    lines, stamps = [], np.array([m.timestamp for m in msgs], dtype=np.float64)
    for k, m in enumerate(msgs):
        r = np.asarray(m.ranges, dtype=np.float64).copy()
        r[(r <= 0.0) | (r >= no_return)] = np.inf
        q = _quarter(k, traits)
        r = returns_with_traits(resample(r, q / 4.0, m.angular_resolution), traits, rng)
        start = m.start_angle + q / 4.0 * m.angular_resolution
        lines.append(robotlaser1_line(r, start, m.angular_resolution, traits.declared_max_range, m.laser_pose,
                                      m.robot_pose, stamps[k] + shift[k], host="hospital-rewrite"))
    return lines, stamps, shift


def shifted_relations(relations: np.ndarray, stamps: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The relations whose two stamps both lie within the scans' span, each stamp moved on by the shift of its
    nearest scan (the logs' stamps need not be sorted: Intel's step back by up to 0.9 s)."""
    rel = np.asarray(relations, dtype=np.float64).reshape(-1, 8)
    inside = ((rel[:, :2] >= stamps.min()) & (rel[:, :2] <= stamps.max())).all(axis=1)
    rel = rel[inside].copy()
    order = np.argsort(stamps, kind="stable")
    sorted_stamps = stamps[order]
    for c in (0, 1):
        right = np.clip(np.searchsorted(sorted_stamps, rel[:, c]), 0, len(stamps) - 1)
        left = np.clip(right - 1, 0, len(stamps) - 1)
        pick = np.where(np.abs(sorted_stamps[left] - rel[:, c]) <= np.abs(sorted_stamps[right] - rel[:, c]), left,
                        right)
        rel[:, c] += shift[order[pick]]
    return rel


def write_rewritten(out: Path, log: Path, relations: Path, traits: HospitalTraits, name: str, seed: int = 0,
                    first: int = 0, count: int | None = None) -> dict:
    """``<name>.clf`` and ``<name>.relations`` into ``out`` (the log rewritten with ``traits``); returns a summary."""
    from dm2_backend.evaluation.relations import load_relations

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lines, stamps, shift = rewrite_lines(log, traits, seed, first, count)
    with atomic_write(out / f"{name}.clf") as fh:
        fh.write(f"# {Path(log).name} rewritten as hospital-like ROBOTLASER1 (dm2_backend.simulate.hospital_rewrite)\n")
        fh.write("\n".join(lines) + "\n")
    rel = shifted_relations(load_relations(relations), stamps, shift)
    with atomic_write(out / f"{name}.relations") as fh:
        fh.writelines(" ".join(f"{v:.6f}" for v in row) + "\n" for row in rel)
    return {"source": str(log), "scans": len(lines), "relations": len(rel), "pause_s": float(shift[-1]),
            "traits": asdict(traits)}
