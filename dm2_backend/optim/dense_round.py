"""One round of the dense stage as a typed record, and its row in ``report.json`` and the checkpoint."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from dm2_backend.optim.odometry_noise import MeasuredNoise

#: the record's whole numbers (counts); every other field but the optional two is a finite number
COUNTS = ("round", "planes", "cells_on_planes", "cg_iterations")


@dataclass(frozen=True)
class Round:
    """A Gauss-Newton round: the objective and its parts (planes, graph), the planes' noise sigma (m), how many
    planes and cells on them, the step it took (rms and largest, m; largest rotation, rad) at which scale and
    damping, and the conjugate-gradient iterations; ``ate``: accuracy against ground truth (recorded, never used
    to decide); ``odometry_noise``: the noise the odometry was weighed by from this round on."""

    round: int
    objective: float
    plane: float
    graph: float
    sigma: float
    planes: int
    cells_on_planes: int
    step_rms_m: float
    step_m: float
    step_rad: float
    scale: float
    damping: float
    cg_iterations: int
    ate: float | None = None
    odometry_noise: MeasuredNoise | None = None

    def row(self) -> dict:
        """The record as ``report.json`` and the checkpoint keep it (the optional fields only when set)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["odometry_noise"] = None if self.odometry_noise is None else self.odometry_noise.summary()
        return {k: v for k, v in out.items() if v is not None or k not in ("ate", "odometry_noise")}

    @classmethod
    def of_row(cls, row: object, frames: int) -> Round:
        """A row read back from a checkpoint of ``frames`` poses: every field present and a number of its kind
        (ValueError)."""
        if not isinstance(row, dict):
            raise ValueError("a round record is not a mapping")
        values = {}
        for f in fields(cls):
            value = row.get(f.name)
            if f.name in ("ate", "odometry_noise"):
                values[f.name] = value
                continue
            whole = f.name in COUNTS
            if isinstance(value, bool) or not isinstance(value, int if whole else int | float) or not math.isfinite(
                    value):
                raise ValueError(f"its round records lack a finite {f.name}")
            values[f.name] = value
        if values["ate"] is not None and not isinstance(values["ate"], int | float):
            raise ValueError("a round record's ate is not a number")
        if values["odometry_noise"] is not None:
            values["odometry_noise"] = MeasuredNoise.of_summary(values["odometry_noise"], frames)
        return cls(**values)
