"""``dm2 plugins``: what is registered under each plugin group, and which optional packages are missing."""

from __future__ import annotations

import importlib.util

import click

from dm2_backend.plugins.registry import GROUPS, discover

#: optional back-ends outside the plugin groups: (what, module, extra)
OPTIONAL = (
    ("baseline g2o", "g2opy", "dm2[g2o]"),
    ("maps: octomap.bt", "pyoctomap", "dm2[maps]"),
    ("maps: mnet_mesh.ply", "skimage", "dm2[maps]"),
    ("dm2 view / refine --rerun", "rerun", "dm2[view]"),
)


def installed(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def status(ep) -> str:
    """"" when the plugin can run; else what is missing and how to install it."""
    try:
        cls = ep.load()
    except ImportError as exc:
        return f"  [cannot load: {exc}]"
    module, extra = getattr(cls, "requires", (None, None))
    if module and not installed(module):
        return f"  [not installed: pip install '{extra}']"
    return ""


@click.command("plugins")
def command() -> None:
    """List the registered warm-start, place-recognition and registration plugins, and the optional
    back-ends, marking what is not installed and how to install it."""
    for group, description in GROUPS.items():
        found = discover(group)
        click.echo(f"{group}  ({description})")
        if not found:
            click.echo("    (none)")
        for name, ep in sorted(found.items()):
            click.echo(f"    {name:<20} {ep.value}{status(ep)}")
    click.echo("optional back-ends")
    for what, module, extra in OPTIONAL:
        state = "installed" if installed(module) else f"not installed: pip install '{extra}'"
        click.echo(f"    {what:<28} {state}")
