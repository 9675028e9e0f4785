"""One first-order epoch as a typed record, and its row in ``report.json`` and the checkpoint."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: the loss terms an epoch may record, in the order of its row
TERMS = ("bce", "chamfer", "consistency")
#: measurements that may be NaN (a map entropy with no neighbourhood of enough points, say)
MAY_BE_NAN = ("ate", "disagreement", "map_entropy")
#: the optional fields of an epoch record and the kind each holds
OPTIONAL = {"bce": float, "chamfer": float, "consistency": float, "ate": float, "ate_metric": str,
             "disagreement": float, "rejected": str, "map_entropy": float, "converged": str}


@dataclass(frozen=True)
class TracePoint:
    """The loss averaged over the steps since the previous point, and the accuracy there (``ate``: recorded
    with a trace metric, never used to decide)."""

    step: int
    loss: float
    ate: float | None = None

    def row(self) -> dict:
        return {"step": self.step, "loss": self.loss, **({} if self.ate is None else {"ate": self.ate})}


@dataclass(frozen=True)
class Epoch:
    """A first-order epoch: its mean loss and loss terms per step, its wall time, the steps taken so far and the
    convergence trace; then what its poses measure: ``ate`` (against ground truth, by ``ate_metric``; recorded,
    never used to decide), their ``disagreement`` with the registrations (m), ``rejected`` (why the epoch
    diverged) or its ``map_entropy``; ``converged``: the early stop after this epoch, in words."""

    epoch: int
    loss: float
    seconds: float
    steps: int
    trace: tuple[TracePoint, ...] = ()
    bce: float | None = None
    chamfer: float | None = None
    consistency: float | None = None
    ate: float | None = None
    ate_metric: str | None = None
    disagreement: float | None = None
    rejected: str | None = None
    map_entropy: float | None = None
    converged: str | None = None

    def row(self) -> dict:
        """The record as ``report.json`` and the checkpoint keep it: the loss terms first, the fields that are
        set only."""
        out = {t: getattr(self, t) for t in TERMS if getattr(self, t) is not None}
        out.update(loss=self.loss, epoch=self.epoch, seconds=self.seconds, steps=self.steps,
                   trace=[p.row() for p in self.trace])
        # the disagreement even when null (no registration was valid to measure against)
        out.update({k: getattr(self, k) for k in OPTIONAL
                    if k not in TERMS and (getattr(self, k) is not None or k == "disagreement")})
        return out

    @classmethod
    def of_row(cls, row: object) -> Epoch:
        """A row read back from a checkpoint, every value checked for its kind (ValueError)."""
        if not isinstance(row, dict):
            raise ValueError("an epoch record is not a mapping")
        values = {"epoch": _whole(row, "epoch"), "steps": _whole(row, "steps"), "loss": _number(row, "loss"),
                  "seconds": _number(row, "seconds")}
        for name, kind in OPTIONAL.items():
            if row.get(name) is not None:
                values[name] = _number(row, name, name in MAY_BE_NAN) if kind is float else _text(row, name)
        trace = row.get("trace", [])
        if not isinstance(trace, list | tuple) or not all(isinstance(p, dict) for p in trace):
            raise ValueError("an epoch's trace is not a list of mappings")
        values["trace"] = tuple(TracePoint(_whole(p, "step"), _number(p, "loss"),
                                           _number(p, "ate", True) if p.get("ate") is not None else None)
                                for p in trace)
        return cls(**values)


def _whole(row: dict, name: str) -> int:
    value = row.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"an epoch record's {name} is not a count")
    return value


def _number(row: dict, name: str, nan: bool = False) -> float:
    value = row.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float) or (math.isnan(value) and not nan):
        raise ValueError(f"an epoch record's {name} is not a number")
    return float(value)


def _text(row: dict, name: str) -> str:
    value = row.get(name)
    if not isinstance(value, str) or len(value) > 1000:
        raise ValueError(f"an epoch record's {name} is not a short text")
    return value

