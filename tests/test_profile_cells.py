"""The consistency profile's cells: a long sequence's cells in temporary files equal those summed in memory and leave
nothing behind; the other frames' sparser map; the flat cells' normals that decide which plane a cell may meet."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from dm2_backend.evaluation import profile_cells, profile_stretches, profile_views
from dm2_backend.kernel.planes import Cells
from dm2_backend.kernel.scans import Scan, ScanSequence


def _sequence(frames: int) -> ScanSequence:
    rng = np.random.default_rng(0)
    scans = [np.concatenate([rng.uniform(-8, 8, (1500, 3)) * [1, 1, 0] + [0, 0, -1.5],  # a floor
                             rng.uniform(-8, 8, (800, 3)) * [0, 1, 0.3] + [6 + i * 0.1, 0, 0]])  # a wall
             for i in range(frames)]
    return ScanSequence(lambda i: Scan(scans[i]), frames, timestamps=np.arange(frames) * 0.1, planar=False)


def test_a_long_sequences_cells_in_files_are_the_cells_in_memory_and_the_files_go(tmp_path, monkeypatch):
    seq = _sequence(7)
    with profile_cells.full_cells(seq, 2.0, 0, False, False) as in_memory:
        expected = Cells(*(np.array(getattr(in_memory, f)) for f in ("frame", "count", "mean", "scatter")),
                         in_memory.size)
    mine = tmp_path / socket.gethostname()  # this machine's folder in a folder machines may share
    stale = mine / ".tmp-999999-profile-left"  # what a killed run of this machine left (no such process)
    stale.mkdir(parents=True)
    elsewhere = tmp_path / "other-host" / ".tmp-999999-profile-live"  # another machine's: not judged here
    elsewhere.mkdir(parents=True)
    monkeypatch.setattr(profile_cells, "ONE_PASS_CELLS", 2 * profile_cells.CELLS_PER_FRAME)  # parts of 2 frames
    with profile_cells.full_cells(seq, 2.0, 0, False, False, folder=tmp_path) as in_files:
        assert isinstance(in_files.mean, np.memmap)
        assert [p.name.startswith(".tmp-") for p in mine.iterdir()] == [True]  # its own folder only
        np.testing.assert_array_equal(in_files.frame, expected.frame)
        np.testing.assert_array_equal(in_files.count, expected.count)
        np.testing.assert_allclose(in_files.mean, expected.mean)
        np.testing.assert_allclose(in_files.scatter, expected.scatter)
    assert list(mine.iterdir()) == [] and elsewhere.is_dir()


def test_the_other_frames_map_keeps_about_its_share_of_each_frame_the_same_under_a_seed():
    count = np.array([0, 10, 500, 2048, 3000])
    bounds = np.concatenate([[0], np.cumsum(count)])
    frame = np.repeat(np.arange(len(count)), count).astype(np.int32)
    k = len(frame)
    cells = Cells(frame, np.ones(k, np.float32), np.zeros((k, 3), np.float32), np.zeros((k, 6), np.float32), 0.1)
    one, again = profile_stretches._sampled(cells, 200, bounds, 3), profile_stretches._sampled(cells, 200, bounds, 3)
    np.testing.assert_array_equal(one.frame, again.frame)
    kept = np.bincount(one.frame, minlength=len(count))
    assert kept[0] == 0 and kept[1] == 10  # a frame with fewer keeps them all
    assert all(abs(kept[i] - 200) < 60 for i in (2, 3, 4)), kept
    assert (np.diff(one.frame) >= 0).all()  # still in frame order


@pytest.mark.parametrize("kind", ["flat", "line", "two points"])
def test_only_a_flat_cell_has_a_normal(kind):
    rng = np.random.default_rng(1)
    if kind == "flat":
        pts = np.c_[rng.uniform(0, 0.2, (50, 2)), rng.normal(0, 0.002, 50)]
    elif kind == "line":
        pts = np.c_[rng.uniform(0, 0.2, 50), rng.normal(0, 0.002, (50, 2))]
    else:
        pts = rng.uniform(0, 0.2, (2, 3))
    d = pts - pts.mean(0)
    scatter = np.array([(d[:, i] * d[:, j]).sum() for i, j in zip(*np.triu_indices(3), strict=True)])
    cells = Cells(np.zeros(1, np.int32), np.array([len(pts)], np.float32), pts.mean(0, keepdims=True),
                  scatter[None].astype(np.float32), 0.2)
    normal = profile_views.flat_normals(cells)[0]
    if kind == "flat":
        assert abs(normal[2]) == pytest.approx(1.0, abs=1e-3)
    else:
        assert np.isnan(normal).all()
