"""``dm2`` entry point: the click group, error handling and sub-command registration."""

from __future__ import annotations

import importlib
import sys
import time
import traceback

import click

from dm2_backend import __version__
from dm2_backend.errors import InputError, did_you_mean
from dm2_backend.progress import setup_logging

#: sub-command name -> module in dm2_backend.cli, imported only when the command is used (start-up stays fast)
COMMANDS = {
    "info": "info", "convert": "convert", "refine": "refine", "baseline": "baseline", "demo": "demo",
    "eval": "eval", "compare": "compare", "plugins": "plugins", "simulate": "simulate",
    "map": "map", "view": "view", "cache": "cache",
}


class Dm2Group(click.Group):
    """Loads sub-commands lazily; turns :class:`InputError` (and OS errors on user files) into one line and
    exit code 2."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        return importlib.import_module(f"dm2_backend.cli.{COMMANDS[name]}").command

    def resolve_command(self, ctx: click.Context, args: list[str]):
        name = click.utils.make_str(args[0]) if args else ""
        if args and name not in COMMANDS and not name.startswith("-"):
            ctx.fail(f"No such command {name!r}.{did_you_mean(name, COMMANDS)}")
        return super().resolve_command(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (InputError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
            if ctx.obj and ctx.obj.get("debug"):
                traceback.print_exc()
            msg = exc.message if isinstance(exc, InputError) else f"{exc.filename}: {exc.strerror}"
            click.echo(f"dm2: error: {msg}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            click.echo("dm2: interrupted", err=True)
            sys.exit(130)


@click.group(cls=Dm2Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="dm2")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """dm2: refine any SLAM trajectory with DeepMapping2."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    ctx.obj.setdefault("started", time.perf_counter())  # a run's "total": the whole command, reading and writing too
    setup_logging()  # stage lines and warnings on stderr, one line each (dm2_backend.progress)


def main() -> None:
    cli(obj={})
