"""The consistency profile's cells: every scan summed once at full density, in memory or, for a long sequence, in a
temporary file that the profile's stretches slice (the scans are read once, never again a stretch at a time)."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dm2_backend.optim.planes import Cells, cells_from_scans
from dm2_backend.progress import progress as progress_of
from dm2_backend.scans import ScanSequence

#: the cells kept per frame (as the dense stage keeps them at most)
CELLS_PER_FRAME = 2048
#: a sequence whose cells fit this many is held in memory (about 45 bytes a cell); a longer one is summed this many
#: at a time into a temporary file (20,000 frames: at most 1.8 GB on disk)
ONE_PASS_CELLS = 6_000_000


def cells_of(scans: ScanSequence, voxel: float, budget: int, seed: int, planar: bool, progress: bool) -> Cells:
    """The profiles' cells of ``scans``: cubes of a quarter voxel in the sensor frame, ``CELLS_PER_FRAME`` a frame
    within ``budget``, every cell's scatter (a judge of the poses, not the dense stage's objective: its settings
    stay those its thresholds were measured with)."""
    # the cubes of a sensor-frame grid: along the beams a jump stands out less against the last frames' scores
    cells = cells_from_scans(scans, voxel / 4.0, CELLS_PER_FRAME, budget, seed, progress, keep_scatter="all",
                             along_beams=False)
    return cells.extruded(voxel) if planar else cells


@contextmanager
def full_cells(scans: ScanSequence, voxel: float, seed: int, planar: bool, progress: bool,
               folder: Path | None = None) -> Iterator[Cells]:
    """Every frame's cells at full density (:func:`cells_of`), in frame order: in memory while ``ONE_PASS_CELLS``
    hold them, else memory-mapped from a temporary file in ``folder`` (default the system's), summed a part of the
    sequence at a time (each part seeded by its first frame) and removed on leaving."""
    n = len(scans)
    if n * CELLS_PER_FRAME <= ONE_PASS_CELLS:
        yield cells_of(scans, voxel, n * CELLS_PER_FRAME, seed, planar, progress)
        return
    part = max(1, ONE_PASS_CELLS // CELLS_PER_FRAME)
    with tempfile.TemporaryDirectory(prefix="dm2-profile-cells-", dir=folder) as tmp:
        rows = n * CELLS_PER_FRAME  # at most; a sparse file holds only the rows written

        def column(name: str, dtype: type, width: int) -> np.ndarray:
            shape = (rows,) if width == 1 else (rows, width)
            return np.lib.format.open_memmap(Path(tmp) / f"{name}.npy", "w+", dtype, shape)

        frame, count = column("frame", np.int32, 1), column("count", np.float32, 1)
        mean, scatter = column("mean", np.float32, 3), column("scatter", np.float32, 6)
        k = 0
        for first in progress_of(range(0, n, part), "profile cells", total=-(-n // part), unit="part",
                                 enabled=progress):
            last = min(n, first + part)
            some = cells_of(scans.subset(np.arange(first, last)), voxel, (last - first) * CELLS_PER_FRAME,
                            seed + first, planar, False)
            end = k + len(some)
            frame[k:end], count[k:end] = some.frame + np.int32(first), some.count
            mean[k:end], scatter[k:end] = some.mean, some.scatter
            k = end
            del some
        size = voxel / 4.0
        yield Cells(frame[:k], count[:k], mean[:k], scatter[:k], size)
        del frame, count, mean, scatter
