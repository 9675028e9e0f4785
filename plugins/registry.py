"""Plugin discovery through Python entry points."""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points

from dm2_backend.runtime.errors import InputError

GROUPS: dict[str, str] = {
    "dm2.warm_start": "initial trajectory",
    "dm2.place_recognition": "map topology: which frames are neighbours",
    "dm2.registration": "pairwise registration between neighbours",
}


def discover(group: str) -> dict[str, EntryPoint]:
    """Entry points registered under ``group``, by name."""
    return {ep.name: ep for ep in entry_points(group=group)}


def load(group: str, name: str):
    """Load plugin ``name`` of ``group``; an :class:`InputError` listing the choices if unknown."""
    found = discover(group)
    if name not in found:
        raise InputError(None, f"no {group} plugin named {name!r}; choices: {', '.join(sorted(found)) or 'none'}")
    return found[name].load()
