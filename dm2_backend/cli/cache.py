"""``dm2 cache``: what the preparation cache holds, and clearing it."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import click

from dm2_backend.cli.suggest import SuggestingGroup
from dm2_backend.prepare.steps import default_cache_dir
from dm2_backend.prepare.store import CACHE_MARKER, is_cache, is_entry
from dm2_backend.runtime.atomic import clean_stale, is_temporary
from dm2_backend.runtime.errors import InputError

path_type = click.Path(path_type=Path)
cache_dir_option = click.option("--cache-dir", type=path_type, default=None,
                                help="Preparation cache (default $DM2_CACHE_DIR or ~/.cache/dm2).")


def entries(root: Path) -> list[tuple[Path, int, float]]:
    """(folder, bytes, age in seconds) of each cache entry (a folder as dm2 writes one), oldest first."""
    out, now = [], time.time()
    for folder in sorted(p for p in root.iterdir() if not p.name.startswith(".") and is_entry(p)):
        files = [f for f in folder.rglob("*") if f.is_file()]
        size = sum(f.stat().st_size for f in files)
        newest = max((f.stat().st_mtime for f in files), default=folder.stat().st_mtime)
        out.append((folder, size, now - newest))
    return sorted(out, key=lambda e: -e[2])


def _age(seconds: float) -> str:
    for unit, span in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= span:
            return f"{seconds / span:.1f} {unit}"
    return f"{seconds:.0f} s"


def _parse_age(text: str) -> float:
    units = {"s": 1, "m": 60, "min": 60, "h": 3600, "d": 86400, "w": 604800}
    number = text.rstrip("".join(units))
    unit = text[len(number):] or "d"
    try:
        return float(number) * units[unit]
    except (KeyError, ValueError) as exc:
        raise click.BadParameter(f"{text!r}: give a number and a unit (s, min, h, d, w), e.g. 7d",
                                 param_hint="--older-than") from exc


@click.group("cache", cls=SuggestingGroup)
def command() -> None:
    """The preparation cache (frames, warm start, topology, registrations) shared by refine and baseline."""


@command.command("info")
@cache_dir_option
def info(cache_dir: Path | None) -> None:
    """Where the cache is, how many entries of each step, their size and age."""
    root = cache_dir or default_cache_dir()
    found = entries(root) if root.is_dir() else []
    click.echo(f"cache      {root}")
    click.echo(f"entries    {len(found)}, {sum(e[1] for e in found) / 2**20:.1f} MiB")
    partial = [p for p in root.iterdir() if is_temporary(p.name)] if root.is_dir() else []
    if partial:
        click.echo(f"partial    {len(partial)} entries being written (or left by a killed run: `dm2 cache clear` "
                   "removes those)")
    kinds: dict[str, list] = {}
    for folder, size, age in found:
        kinds.setdefault(folder.name.split("-")[0], []).append((size, age))
    for kind, rows in sorted(kinds.items()):
        oldest = max(age for _, age in rows)
        click.echo(f"  {kind:<10} {len(rows):4d} entries, {sum(s for s, _ in rows) / 2**20:9.1f} MiB, "
                   f"oldest {_age(oldest)}")


@command.command("clear")
@cache_dir_option
@click.option("--older-than", default=None, help="Only entries written longer ago than this (e.g. 7d, 12h).")
def clear(cache_dir: Path | None, older_than: str | None) -> None:
    """Remove cache entries (all, or those older than --older-than)."""
    root = cache_dir or default_cache_dir()
    limit = _parse_age(older_than) if older_than else -1.0
    removed = freed = 0
    if root.is_dir() and not is_cache(root):
        raise InputError(root, f"is not a dm2 cache (no {CACHE_MARKER} file, which dm2 writes into its cache): "
                               "nothing removed")
    if root.is_dir():  # partial entries of killed runs, whatever their age
        for path in clean_stale(root):
            click.echo(f"removed a partial entry left by a killed run: {path.name}")
    for folder, size, age in (entries(root) if root.is_dir() else []):
        if age > limit:
            shutil.rmtree(folder, ignore_errors=True)
            removed, freed = removed + 1, freed + size
    click.echo(f"removed {removed} entries ({freed / 2**20:.1f} MiB) from {root}")
