"""An epoch record's row (``report.json``, the checkpoint) reads back as the same record; a damaged row is refused."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dm2_backend.optim.epoch import OPTIONAL, TERMS, Epoch, TracePoint

numbers = st.floats(allow_nan=False, width=64)
counts = st.integers(0, 10**6)
points = st.builds(TracePoint, counts, numbers, st.none() | numbers)
optional = st.fixed_dictionaries({}, optional={k: (numbers if kind is float else st.text(max_size=40))
                                             for k, kind in OPTIONAL.items()})


@given(counts, numbers, numbers, counts, st.lists(points, max_size=4), optional)
def test_an_epoch_row_reads_back_as_the_same_record(epoch, loss, seconds, steps, trace, extra):
    record = Epoch(epoch, loss, seconds, steps, tuple(trace), **extra)
    row = record.row()
    assert Epoch.of_row(row) == record
    assert list(row)[: len(set(TERMS) & set(extra))] == [t for t in TERMS if t in extra]  # the loss terms first
    assert all(v is not None for k, v in row.items() if k != "disagreement")  # unset fields are left out
    assert "disagreement" in row  # null where no registration was valid to measure against


def test_a_measurement_may_be_nan_a_loss_may_not():
    row = Epoch(0, 1.0, 2.0, 3, map_entropy=math.nan, ate=math.nan).row()
    back = Epoch.of_row(row)
    assert math.isnan(back.map_entropy) and math.isnan(back.ate)
    with pytest.raises(ValueError, match="loss"):
        Epoch.of_row({**row, "loss": math.nan})


@pytest.mark.parametrize("damage", [{"loss": math.nan}, {"epoch": -1}, {"steps": True}, {"ate": "far"},
                                    {"rejected": 1.0}, {"trace": [{"step": 1}]}, {"trace": "none"}])
def test_a_damaged_row_is_refused(damage):
    row = Epoch(0, 1.0, 2.0, 3, (TracePoint(3, 1.0),), map_entropy=-4.0).row()
    with pytest.raises(ValueError, match="epoch"):
        Epoch.of_row({**row, **damage})
