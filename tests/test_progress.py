"""Progress output: a bar only on a terminal, otherwise one log line per stage; status updates never force a
redraw; a small run through the CLI writes no carriage-return redraws and one line per stage."""

from __future__ import annotations

import io
import logging
import re

from click.testing import CliRunner

from dm2_backend.cli.main import cli
from dm2_backend.runtime.progress import progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_no_terminal_no_bar_and_one_line(caplog):
    stream = io.StringIO()
    with caplog.at_level(logging.INFO, logger="dm2_backend.runtime.progress"):
        bar = progress(range(50), "loop closure", enabled=True, stream=stream)
        for i in bar:
            bar.set_postfix(closures=i)
    assert stream.getvalue() == ""
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith("loop closure: 50/50 in ") and line.endswith(" s (closures=49)")


def test_status_updates_do_not_redraw_the_bar():
    stream = Terminal()
    bar = progress(range(2000), "loop closure", stream=stream)
    for i in bar:
        bar.set_postfix(closures=i)
    assert 0 < stream.getvalue().count("\r") < 20  # redrawn at most every 0.5 s, not once per closure


def test_disabled_is_silent(caplog):
    stream = Terminal()
    with caplog.at_level(logging.INFO, logger="dm2_backend.runtime.progress"):
        assert list(progress(range(3), "quiet", enabled=False, stream=stream)) == [0, 1, 2]
    assert stream.getvalue() == "" and not caplog.records


def test_small_run_logs_one_line_per_stage(tmp_path):
    result = CliRunner().invoke(cli, ["demo", "--frames", "60", "--epochs", "1", "--out", str(tmp_path / "d")],
                                obj={})
    assert result.exit_code == 0, result.output
    err = result.stderr
    assert "\r" not in err and "it/s" not in err, err
    lines = err.splitlines()
    for stage in ("simulate", "load scans", "loop closure", "pairwise icp", "map scans", "dense cells", "dense"):
        mine = [ln for ln in lines if re.match(rf"dm2: {stage}: \d+/\d+ in ", ln)]  # its progress line, once
        assert len(mine) == 1, (stage, err)
    assert not [ln for ln in lines if ln.startswith("dm2: refine: ")]  # no first-order epochs after the dense stage
