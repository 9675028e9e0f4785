"""Isolated long returns of planar scans (glass, open doors) are dropped, real structure is kept
(:mod:`dm2_backend.kernel.planar_returns`, applied by the CARMEN reader)."""

from __future__ import annotations

import math

import numpy as np

from dm2_backend.formats.carmen import open_carmen_scans, robotlaser1_line
from dm2_backend.kernel.planar_returns import isolated_long_returns

STEP = math.radians(1.0)
ANGLES = -math.pi / 2 + STEP * np.arange(181)


def cast(segments: list[tuple[tuple[float, float], tuple[float, float]]], angles: np.ndarray) -> np.ndarray:
    """Ranges from the origin along ``angles`` to the nearest of ``segments`` (inf where none is hit)."""
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    best = np.full(len(angles), np.inf)
    for (ax, ay), (bx, by) in segments:
        e = np.array([bx - ax, by - ay])
        den = d[:, 0] * e[1] - d[:, 1] * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * e[1] - ay * e[0]) / den  # along the ray
            u = (ax * d[:, 1] - ay * d[:, 0]) / den  # along the segment
        hit = np.isfinite(t) & (t > 0) & (u >= 0) & (u <= 1)
        best[hit] = np.minimum(best[hit], t[hit])
    return best


def room() -> list:
    """A room with a corner, a recess (a doorway 1.5 m wide, a wall behind it), a pillar and a thin post: walls
    seen at every incidence, jumps between surfaces, short returns among long ones."""
    return [((6.0, -8.0), (6.0, -1.0)), ((6.0, -1.0), (9.0, -1.0)), ((9.0, -1.0), (9.0, 0.5)),
            ((9.0, 0.5), (6.0, 0.5)), ((6.0, 0.5), (6.0, 3.0)), ((6.0, 3.0), (2.0, 7.0)),
            ((2.0, 7.0), (-5.0, 7.0)), ((6.0, -8.0), (-5.0, -8.0)), ((-5.0, -8.0), (-5.0, 7.0)),
            ((3.0, -2.0), (3.4, -2.0)), ((3.4, -2.0), (3.4, -1.6)), ((3.0, 4.0), (3.02, 4.0))]


def test_real_structure_is_kept():
    r = cast(room(), ANGLES)
    r += np.random.default_rng(0).normal(0.0, 0.01, len(r))
    valid = np.isfinite(r)
    assert valid.all()
    assert not isolated_long_returns(r, valid, STEP).any()


def test_isolated_long_returns_are_dropped_and_nothing_else():
    rng = np.random.default_rng(1)
    clean = cast(room(), ANGLES) + rng.normal(0.0, 0.01, len(ANGLES))
    for _ in range(20):
        r = clean.copy()
        valid = rng.uniform(size=len(r)) > 0.08  # max-range codes: the long return's neighbour may be missing
        spurious = np.zeros(len(r), bool)
        spurious[rng.choice(np.arange(1, len(r) - 1), 8, replace=False)] = True
        spurious &= valid
        spurious[1:] &= ~spurious[:-1]  # isolated: not next to another
        spurious[:-1] &= ~spurious[1:]
        r[spurious] = rng.uniform(30.0, 50.0, int(spurious.sum()))
        found = isolated_long_returns(r, valid, STEP)
        # every long return whose nearest valid neighbours lie on one wall (not across the room's jumps) is found
        left = np.array([max((k for k in range(i) if valid[k]), default=-1) for i in range(len(r))])
        right = np.array([min((k for k in range(i + 1, len(r)) if valid[k]), default=-1) for i in range(len(r))])
        same = (left >= 0) & (right >= 0) & (np.abs(clean[left] - clean[right]) < 0.1 * (right - left))
        assert found[spurious & same].all()
        assert not found[~spurious].any()


def test_the_carmen_reader_drops_them(tmp_path):
    """A ROBOTLASER1 log: the isolated long returns are read as no point, the walls next to them stay."""
    r = cast(room(), ANGLES)
    spurious = np.array([20, 60, 140])
    r[spurious] = [35.0, 42.0, 48.0]
    lines = [robotlaser1_line(r, float(ANGLES[0]), STEP, 81.91, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), t) for t in (1, 2)]
    (tmp_path / "log.clf").write_text("\n".join(lines) + "\n")
    points = open_carmen_scans(tmp_path / "log.clf")[0].points
    assert len(points) == len(ANGLES) - len(spurious)
    assert np.linalg.norm(points[:, :2], axis=1).max() < 15.0


def test_aces_rewritten_with_long_returns_reads_like_the_clean_rewrite(tmp_path):
    """Real data: 400 scans of ACES with 4 % of their near returns made isolated long returns (30-50 m) read back with
    most of them dropped, and with nearly every other point of the clean rewrite (real structure is kept; ACES has
    real returns beyond 30 m too)."""
    import sys
    from pathlib import Path

    import pytest

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from hospital_real_logs import DATA, cases

    from dm2_backend.simulate.hospital_rewrite import write_rewritten

    aces = DATA / "aces.clf.bz2"
    if not aces.exists():
        pytest.skip(f"{aces} absent")
    far, kept = {}, {}
    for name in ("clean", "long returns"):
        write_rewritten(tmp_path, aces, DATA / "aces.relations", cases()[name], name.replace(" ", "-"), count=400)
        seq = open_carmen_scans(tmp_path / f"{name.replace(' ', '-')}.clf")
        r = np.concatenate([np.linalg.norm(seq[i].points[:, :2], axis=1) for i in range(len(seq))])
        far[name], kept[name] = int((r > 30.0).sum()), len(r)
    spurious = 0.04 * kept["clean"]  # about how many long returns the rewrite made
    # most of them dropped (not those next to a no-return or between two surfaces: 78 % on these scans)
    assert far["long returns"] - far["clean"] < 0.33 * spurious, (far, kept)
    assert kept["long returns"] > kept["clean"] - 1.1 * spurious, (far, kept)  # beyond them, little else lost
