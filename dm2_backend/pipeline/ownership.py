"""What dm2 wrote, known by content: an entry of a run folder is dm2's only while it holds what dm2 put there.

A run records the identity of every entry it writes as it writes it (:class:`Written`): a file's size and
content digest, a folder's every file (relative path, size, digest). ``--force`` and the cleanup after a failure
remove an entry only while its identity still matches (:func:`identity`); one that changed since, one whose
writing was cut short, and anything that is not a plain file or a folder of plain files (a link, a FIFO) are
left where they are.
"""

from __future__ import annotations

import hashlib
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

CHUNK = 1 << 20


def file_identity(path: str | Path) -> str | None:
    """``size:digest`` of a plain file (not followed through a link); None for anything else."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0) | os.O_NONBLOCK)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            return None
        h = hashlib.sha1()
        while block := fh.read(CHUNK):
            h.update(block)
    return f"{st.st_size}:{h.hexdigest()[:20]}"


def tree_identity(files: dict[str, str]) -> str:
    """The identity of a folder from its files' (relative path -> :func:`file_identity`)."""
    h = hashlib.sha1()
    for rel in sorted(files):
        h.update(f"{rel}\0{files[rel]}\n".encode())
    return f"tree:{len(files)}:{h.hexdigest()[:20]}"


def identity(path: Path) -> str | None:
    """What ``path`` holds now: :func:`file_identity` for a file, :func:`tree_identity` for a folder of plain files
    and folders; None for a link, a FIFO, a folder holding one, or what cannot be read."""
    try:
        mode = path.lstat().st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode):
        return file_identity(path)
    if not stat.S_ISDIR(mode):
        return None
    files: dict[str, str] = {}
    for root, dirs, names in os.walk(path, onerror=_raise):
        for name in dirs:
            if os.path.islink(os.path.join(root, name)):
                return None
        for name in names:
            full = os.path.join(root, name)
            ident = file_identity(full)
            if ident is None:
                return None
            files[os.path.relpath(full, path)] = ident
    return tree_identity(files)


def _raise(exc: OSError) -> None:
    raise exc


def still_ours(path: Path, recorded: str | None) -> bool:
    """Whether ``path`` holds exactly what dm2 recorded it wrote there."""
    if recorded is None:
        return False
    try:
        return identity(path) == recorded
    except OSError:
        return False


@dataclass
class Written:
    """The identities of the top-level entries of ``root`` written meanwhile: a file or a folder placed whole is
    identified when it is in place; the files written one by one into a folder are identified as they come, and the
    folder's identity made from them (:meth:`identities`)."""

    root: Path
    whole: dict[str, str | None] = field(default_factory=dict)
    parts: dict[str, dict[str, str | None]] = field(default_factory=dict)

    def placed(self, path: Path) -> str | None:
        """Record ``path`` (in place under its name); returns its top-level name, None if outside ``root``."""
        try:
            rel = Path(os.path.abspath(path)).relative_to(os.path.abspath(self.root))
        except ValueError:
            return None
        if not rel.parts:
            return None
        name = rel.parts[0]
        if len(rel.parts) == 1:
            self.whole[name] = identity(self.root / name)
            self.parts.pop(name, None)
        else:
            self.parts.setdefault(name, {})[str(Path(*rel.parts[1:]))] = file_identity(path)
            self.whole.pop(name, None)
        return name

    def identities(self) -> dict[str, str]:
        """Name -> identity of everything recorded whole (None-free: an entry that was not a plain file or
        folder is nobody's to remove)."""
        out = {name: ident for name, ident in self.whole.items() if ident is not None}
        for name, files in self.parts.items():
            if all(ident is not None for ident in files.values()):
                out[name] = tree_identity(files)  # type: ignore[arg-type]
        return out

    def parts_of(self, name: str) -> dict[str, str | None]:
        """The files written one by one into folder ``name`` (relative path -> identity)."""
        return dict(self.parts.get(name, {}))
