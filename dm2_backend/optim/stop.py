"""Why an optimisation stopped: a :class:`StopReason` and the sentence that says where."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class StopReason(str, enum.Enum):
    """Why the rounds (dense stage) or epochs (first-order stage) ended."""

    #: no round or epoch was asked for (the first-order epochs after the dense stage, by default)
    NOT_RUN = "not run"
    #: every round or epoch asked for ran
    BUDGET = "budget"
    #: the steps, or the loss and the map, stopped changing
    CONVERGED = "converged"
    #: no step lowered the objective
    NO_DESCENT = "no descent"
    #: a loss was not finite; the best epoch before it is kept
    NON_FINITE = "non-finite"
    #: every epoch disagreed with the registrations; the start is returned
    DIVERGED = "diverged"


@dataclass(frozen=True)
class Stop:
    """A :class:`StopReason` and the sentence that says where (round or epoch) and by how much."""

    reason: StopReason
    detail: str

    def __str__(self) -> str:
        return self.detail

    @property
    def failed(self) -> bool:
        """The stage ended on a failure the user is warned about (a non-finite loss, every epoch diverged)."""
        return self.reason in (StopReason.NON_FINITE, StopReason.DIVERGED)
