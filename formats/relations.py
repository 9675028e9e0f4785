"""Freiburg SLAM benchmark relations (Kümmerle et al. 2009): ``t1 t2 x y z roll pitch yaw`` per line, the
relative pose between the robot at two timestamps; ``#`` comments; plain, ``.gz`` or ``.bz2``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2_backend.formats.carmen_parser import _num, read_text
from dm2_backend.runtime.errors import InputError

_RELATION_FIELDS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")


def read_relations(path: str | Path) -> np.ndarray:
    """Freiburg benchmark relations ``t1 t2 x y z roll pitch yaw`` as an (M, 8) float64 array."""
    path = Path(path)
    rows = []
    for no, line in enumerate(read_text(path).split("\n"), start=1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) != 8:
            raise InputError(
                path, f"a relation has 8 values (t1 t2 x y z roll pitch yaw), found {len(words)}", line=no
            )
        rows.append([_num(w, name, path, no) for w, name in zip(words, _RELATION_FIELDS, strict=True)])
    if not rows:
        raise InputError(path, "no relations")
    return np.array(rows, dtype=np.float64)
