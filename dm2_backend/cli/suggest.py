"""The "did you mean" of a mistyped name, the same everywhere: ``dm2 refin``, ``dm2 cache inf`` and
``dm2 baseline gtsm`` all end with ``(did you mean 'refine'?)`` (:func:`dm2_backend.runtime.errors.did_you_mean`).

Light on purpose (click only): sub-commands import it at start-up."""

from __future__ import annotations

import click

from dm2_backend.runtime.errors import did_you_mean


class Choice(click.Choice):
    """:class:`click.Choice` whose refusal of a value names the closest choice."""

    def convert(self, value, param, ctx):
        try:
            return super().convert(value, param, ctx)
        except click.BadParameter as exc:
            exc.message += did_you_mean(value, self.choices)
            raise


class SuggestingGroup(click.Group):
    """A sub-group (``dm2 cache``) whose unknown sub-command names the closest one, as the top-level
    ``dm2`` group does."""

    def resolve_command(self, ctx: click.Context, args: list[str]):
        name = click.utils.make_str(args[0]) if args else ""
        commands = self.list_commands(ctx)
        if args and name not in commands and not name.startswith("-") and not ctx.resilient_parsing:
            ctx.fail(f"No such command {name!r}.{did_you_mean(name, commands)}")
        return super().resolve_command(ctx, args)
