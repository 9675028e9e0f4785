"""``dm2`` entry point: the click group, error handling and sub-command registration."""

from __future__ import annotations

import errno
import importlib
import shlex
import signal
import sys
import time
import traceback

import click

from dm2_backend import __version__
from dm2_backend.runtime.errors import InputError, did_you_mean, one_line
from dm2_backend.runtime.progress import setup_logging

#: OS errors on the user's files and folders that are a one-line error, not a traceback
USER_OS_ERRORS = {errno.ENOENT: None, errno.EISDIR: None, errno.EACCES: None, errno.EPERM: None,
                  errno.ELOOP: "too many levels of symbolic links (a symlink loop)", errno.ENOTDIR: None,
                  errno.ENAMETOOLONG: None, errno.EROFS: "read-only file system",
                  errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
                  errno.EFBIG: "file size limit reached"}

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

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta["dm2.argv"] = list(args)  # the command as typed: named again after an interruption
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        argv = ctx.meta.get("dm2.argv", [])
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:  # e.g. --epochs 1e9: one line, not click's usage block
            if exc.ctx is None or exc.ctx.parent is None:
                raise
            click.echo(f"dm2: error: {one_line(exc.format_message())} (see dm2 {exc.ctx.info_name} -h)", err=True)
            sys.exit(2)
        except (InputError, OSError) as exc:
            if isinstance(exc, OSError) and exc.errno not in USER_OS_ERRORS:
                raise
            if ctx.obj and ctx.obj.get("debug"):
                traceback.print_exc()
            if isinstance(exc, InputError):
                msg = exc.message
            else:
                msg = InputError(exc.filename, USER_OS_ERRORS[exc.errno] or exc.strerror or str(exc)).message
            click.echo(f"dm2: error: {msg}", err=True)
            sys.exit(2)
        except KeyboardInterrupt as exc:
            click.echo(f"dm2: {interruption(exc, argv)}", err=True)
            sys.exit(130)


def interruption(exc: KeyboardInterrupt, argv: list[str]) -> str:
    """The interruption line: the signal, what was kept, and the command to run next."""
    signame = getattr(exc, "signal_name", None) or getattr(exc.__cause__, "signal_name", None) or "Ctrl-C"
    text = f"interrupted ({signame})"
    next_step = getattr(exc, "next_step", None)
    if next_step is None:
        return text
    again = [a for a in argv if a != "--force"] if exc.resume else argv
    if exc.resume and "--resume" not in again:
        again.append("--resume")
    return f"{text}: {next_step}: dm2 {shlex.join(again)}"


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a job scheduler, ``docker stop``, a closed terminal): handled like Ctrl-C."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def _terminate(signum: int, frame) -> None:
    raise Terminated(signal.Signals(signum).name)


def handle_termination() -> None:
    """SIGTERM and SIGHUP raise :class:`Terminated` (a KeyboardInterrupt), so that they end a run like Ctrl-C:
    its folder released, its checkpoint listed, one line naming the next command."""
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _terminate)


@click.group(cls=Dm2Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="dm2")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """dm2: refine any SLAM trajectory with DeepMapping2."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    ctx.obj.setdefault("started", time.perf_counter())  # a run's "total": the whole command, reading and writing too
    setup_logging()  # stage lines and warnings on stderr, one line each (dm2_backend.runtime.progress)


def main() -> None:
    handle_termination()
    cli(obj={})
