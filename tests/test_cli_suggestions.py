"""A mistyped name gets the same "did you mean" everywhere (issue 53, item 4): the top-level command
(``dm2 refin``), a sub-group's command (``dm2 cache inf``) and a choice (``dm2 baseline gtsm``, ``--robust``)."""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from dm2_backend.cli.main import COMMANDS, Dm2Group, cli


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], obj={})


def one_line(result, *parts) -> None:
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert "\n" not in err and "Traceback" not in result.output, err
    for part in parts:
        assert part in err, err


@pytest.mark.parametrize("args, suggestion", [
    (["baseline", "gtsm"], "(did you mean 'gtsam'?)"),
    (["baseline", "g2"], "(did you mean 'g2o'?)"),
    (["cache", "inf"], "(did you mean 'info'?)"),
    (["cache", "clr"], "(did you mean 'clear'?)"),
    (["baseline", "gtsam", "--robust", "cachy"], "(did you mean 'cauchy'?)"),
    (["refine", "--device", "cuad"], "(did you mean 'cuda'?)"),
    (["eval", "--align", "se33"], "(did you mean 'se3'?)"),
    (["convert", "a.tum", "b.txt", "--duplicate-times", "keep-frst"], "(did you mean 'keep-first'?)"),
])
def test_sub_commands_suggest_as_the_top_level_does(args, suggestion):
    one_line(run(*args), suggestion)


def test_top_level_wording_is_the_same():
    r = run("refin")
    assert r.exit_code == 2 and "(did you mean 'refine'?)" in r.output


def test_every_sub_group_and_choice_suggests():
    """No sub-group or choice of any command is left with click's own (or no) suggestion."""
    from dm2_backend.cli.suggest import Choice, SuggestingGroup

    ctx = click.Context(cli)
    for name in COMMANDS:
        stack = [Dm2Group.get_command(cli, ctx, name)]
        while stack:
            command = stack.pop()
            if isinstance(command, click.Group):
                assert isinstance(command, SuggestingGroup), f"dm2 {name}: {command.name} is a plain click group"
                stack += list(command.commands.values())
            for param in command.params:
                if isinstance(param.type, click.Choice):
                    assert isinstance(param.type, Choice), f"dm2 {name} {param.name}: a plain click.Choice"


def test_no_suggestion_when_nothing_is_close():
    r = run("baseline", "zzzzzz")
    one_line(r, "'zzzzzz' is not one of")
    assert "did you mean" not in r.stderr
