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


def relative_in(root: Path, path: Path) -> Path | None:
    """``path`` relative to ``root`` when it lies inside it (not ``root`` itself), else None."""
    try:
        rel = Path(os.path.abspath(path)).relative_to(os.path.abspath(root))
    except ValueError:
        return None
    return rel if rel.parts else None


@dataclass
class Written:
    """The identities of the top-level entries of ``root`` written meanwhile: a file or a folder placed whole is
    identified when it is in place; the files written one by one into a folder are identified as they come, and the
    folder's identity made from them (:meth:`identities`)."""

    root: Path
    whole: dict[str, str | None] = field(default_factory=dict)
    parts: dict[str, dict[str, str | None]] = field(default_factory=dict)

    def placed(self, path: Path, source: Path | None = None) -> str | None:
        """Record what ``path`` holds, read from ``source`` (the temporary about to be renamed to it; default the
        path itself); returns its top-level name, None if outside ``root``."""
        rel = relative_in(self.root, path)
        if rel is None:
            return None
        name, source = rel.parts[0], Path(source if source is not None else path)
        if len(rel.parts) == 1:
            try:
                self.whole[name] = identity(source)
            except OSError:  # unreadable: nobody's to remove
                self.whole[name] = None
            self.parts.pop(name, None)
        else:
            self.parts.setdefault(name, {})[str(Path(*rel.parts[1:]))] = file_identity(source)
            self.whole.pop(name, None)
        return name

    def recorded(self, rel: Path) -> str | None:
        """The identity recorded for ``rel`` (relative to the root): a top-level entry's, or a file's written into
        a folder one by one."""
        if len(rel.parts) == 1:
            return self.whole.get(rel.parts[0])
        return self.parts.get(rel.parts[0], {}).get(str(Path(*rel.parts[1:])))

    def identities(self) -> dict[str, str]:
        """Name -> identity of each top-level entry: placed whole, or a folder whose files were all placed one by
        one (None-free: an entry that was not a plain file or folder is nobody's to remove)."""
        out = {name: ident for name, ident in self.whole.items() if ident is not None}
        for name, files in self.parts.items():
            if all(ident is not None for ident in files.values()):
                out[name] = tree_identity(files)  # type: ignore[arg-type]
        return out

    def parts_of(self, name: str) -> dict[str, str | None]:
        """The files written one by one into folder ``name`` (relative path -> identity)."""
        return dict(self.parts.get(name, {}))
