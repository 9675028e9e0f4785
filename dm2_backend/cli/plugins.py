"""``dm2 plugins``: what is registered under each plugin group."""

from __future__ import annotations

import click

from dm2_backend.plugins.registry import GROUPS, discover


@click.command("plugins")
def command() -> None:
    """List the registered warm-start, place-recognition and registration plugins."""
    for group, description in GROUPS.items():
        found = discover(group)
        click.echo(f"{group}  ({description})")
        if not found:
            click.echo("    (none)")
        for name, ep in sorted(found.items()):
            click.echo(f"    {name:<20} {ep.value}")
