"""The consistency profile's cells: every scan summed once at full density, in memory or, for a long sequence, in
temporary files that the profile's stretches map read-only (the scans are read once, never again a stretch at a
time)."""

from __future__ import annotations

import socket
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.kernel.planes import Cells, cells_from_scans
from dm2_backend.kernel.scans import ScanSequence
from dm2_backend.runtime.atomic import clean_stale, no_space_error, temp_prefix
from dm2_backend.runtime.errors import InputError, one_line
from dm2_backend.runtime.progress import progress as progress_of

#: the cells kept per frame (as the dense stage keeps them at most)
CELLS_PER_FRAME = 2048
#: a sequence whose cells fit this many is held in memory (about 45 bytes a cell); a longer one is summed this many
#: at a time into temporary files (20,000 frames: at most 1.8 GB on disk)
ONE_PASS_CELLS = 6_000_000
#: the columns of :class:`Cells` in the files: name, type, shape of a row
COLUMNS = (("frame", np.int32, ()), ("count", np.float32, ()), ("mean", np.float32, (3,)),
           ("scatter", np.float32, (6,)))


def cells_of(scans: ScanSequence, voxel: float, budget: int, seed: int, planar: bool, progress: bool) -> Cells:
    """The profiles' cells of ``scans``: cubes of a quarter voxel in the sensor frame, ``CELLS_PER_FRAME`` a frame
    within ``budget``, every cell's scatter (a judge of the poses, not the dense stage's objective: its settings
    stay those its thresholds were measured with)."""
    # the cubes of a sensor-frame grid: along the beams a jump stands out less against the last frames' scores
    cells = cells_from_scans(scans, voxel / 4.0, CELLS_PER_FRAME, budget, seed, progress, keep_scatter="all",
                             along_beams=False)
    return cells.extruded(voxel) if planar else cells


def cells_folder(folder: Path | None = None) -> Path:
    """Where a long sequence's cells are kept while it is profiled: this machine's folder in ``folder`` (storage
    several machines may share), by default ``dm2-profile-cells`` in the system's temporary folder; dm2's alone:
    what an ended run of this machine left there is removed first."""
    parent = Path(folder) / socket.gethostname() if folder is not None else (
        Path(tempfile.gettempdir()) / "dm2-profile-cells")
    parent.mkdir(parents=True, exist_ok=True)
    clean_stale(parent)
    return parent


@dataclass(frozen=True)
class StoredCells:
    """Where :func:`full_cells` keeps a long sequence's cells: its files in ``folder``, ``rows`` cells of edge
    ``size``; what a task on another process needs to map them (the folder on storage every worker sees)."""

    folder: Path
    rows: int
    size: float

    @classmethod
    def of(cls, cells: Cells) -> StoredCells | None:
        """Where ``cells`` are stored, None for cells held in memory."""
        if not isinstance(cells.frame, np.memmap) or cells.frame.filename is None:
            return None
        return cls(Path(cells.frame.filename).parent, len(cells), cells.size)

    def open(self) -> Cells:
        """The cells, mapped read-only; a folder this process cannot read (a worker on another machine without
        it): one line."""
        try:
            return Cells(*(np.memmap(self.folder / f"{name}.bin", dtype, "r", shape=(self.rows, *shape))
                           for name, dtype, shape in COLUMNS), self.size)
        except (OSError, ValueError) as exc:
            raise InputError(self.folder, "the consistency profile's cells cannot be read there "
                                          f"({one_line(str(exc))[:120]}); on several machines give --cache-dir on "
                                          "storage every worker sees") from None


@contextmanager
def full_cells(scans: ScanSequence, voxel: float, seed: int, planar: bool, progress: bool,
               folder: Path | None = None, stored: bool = False) -> Iterator[Cells]:
    """Every frame's cells at full density (:func:`cells_of`), in frame order: in memory while ``ONE_PASS_CELLS``
    hold them, else appended a part of the sequence at a time (each part seeded by its first frame) to files in
    :func:`cells_folder`, mapped read-only (``memory.release_mapped`` drops their pages; :meth:`StoredCells.of`
    says where) and removed on leaving. ``stored``: in files even where they fit in memory (then summed in one
    part, with the same seed: the same cells). Out of disk space: one line (``InputError``)."""
    n = len(scans)
    one_pass = n * CELLS_PER_FRAME <= ONE_PASS_CELLS
    if one_pass and not stored:
        yield cells_of(scans, voxel, n * CELLS_PER_FRAME, seed, planar, progress)
        return
    part = max(1, n if one_pass else ONE_PASS_CELLS // CELLS_PER_FRAME)
    with tempfile.TemporaryDirectory(prefix=f"{temp_prefix()}profile-", dir=cells_folder(folder),
                                     ignore_cleanup_errors=True) as tmp:  # (a file a worker still maps, on NFS)
        path = {name: Path(tmp) / f"{name}.bin" for name, _, _ in COLUMNS}
        rows = 0
        try:
            with ExitStack() as stack:
                files = {name: stack.enter_context(open(p, "wb")) for name, p in path.items()}
                for first in progress_of(range(0, n, part), "profile cells", total=-(-n // part), unit="part",
                                         enabled=progress and not one_pass):
                    some = cells_of(scans.subset(np.arange(first, min(n, first + part))), voxel,
                                    part * CELLS_PER_FRAME, seed + first, planar, progress and one_pass)
                    some.frame += np.int32(first)
                    for name, dtype, _ in COLUMNS:
                        np.ascontiguousarray(getattr(some, name), dtype).tofile(files[name])
                    rows += len(some)
        except OSError as exc:
            raise (no_space_error(exc, path["scatter"]) or exc) from exc
        if rows == 0:  # no scan had a point
            yield Cells(*(np.zeros((0, *shape), dtype) for _, dtype, shape in COLUMNS), voxel / 4.0)
            return
        yield StoredCells(Path(tmp), rows, voxel / 4.0).open()
