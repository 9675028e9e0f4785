"""Cache keys of the preparation steps: everything that determines a step's result, and nothing else.

A step's key hashes the key of the step before it, the step's plugin name and options, and the *code* that
computes it (the plugin's module and every dm2 module it reaches, by source text). The first step's key also
hashes the input itself: the scan source's read spec (format, path and every read option) and, for every file
the reading depends on (the source, ``--times``, ``--calib``), its size, modification time, inode change time
and a digest of its first and last 4 KiB, file by file through folders (overwriting scans in place does not
change a folder's own mtime; ``touch -r`` can set an mtime back, but not the change time, nor the content).
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import os
import stat
import sys
import types
from pathlib import Path

from dm2_backend import __version__
from dm2_backend.kernel.scans import ScanSequence

#: read-spec entries that name files whose content the reading depends on
FILE_OPTIONS = ("path", "times", "calib")


def step_key(*parts) -> str:
    """A short hash of ``parts`` (JSON, sorted keys) and the dm2 version."""
    blob = json.dumps([__version__, *parts], sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:16]


#: bytes read from each end of a file for its content digest
EDGE_BYTES = 4096


def _edges(path: str, size: int) -> str:
    """A short digest of the first and last :data:`EDGE_BYTES` of a regular file ('' if unreadable)."""
    h = hashlib.sha1()
    try:
        with open(path, "rb") as fh:
            h.update(fh.read(EDGE_BYTES))
            if size > EDGE_BYTES:
                fh.seek(max(EDGE_BYTES, size - EDGE_BYTES))
                h.update(fh.read(EDGE_BYTES))
    except OSError:
        return ""
    return h.hexdigest()[:16]


def _stat_line(full: str, st: os.stat_result) -> str:
    edges = _edges(full, st.st_size) if stat.S_ISREG(st.st_mode) else ""
    return f"{st.st_size}\0{st.st_mtime_ns}\0{st.st_ctime_ns}\0{edges}"


def file_fingerprint(path: str | Path | None) -> list:
    """``[size, mtime_ns, ctime_ns, edge digest]`` of a file; of a folder, a hash of the same for every file
    under it (with its relative name); ``[]`` when there is no such path."""
    if not path:
        return []
    path = Path(path)
    if path.is_file():
        st = path.stat()
        return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, _edges(str(path), st.st_size)]
    if not path.is_dir():
        return []
    h = hashlib.sha1()
    for root, dirs, files in os.walk(path):
        dirs.sort()
        for name in sorted(files):
            full = os.path.join(root, name)
            try:
                st = os.stat(full)
            except OSError:
                continue
            h.update(f"{os.path.relpath(full, path)}\0{_stat_line(full, st)}\n".encode())
    return [h.hexdigest()]


def source_key(scans: ScanSequence) -> list:
    """What the frames depend on: the read spec, the fingerprint of each file it names, and the scan count."""
    spec = dict(scans.read_spec) or {"path": scans.source}
    files = {name: file_fingerprint(spec.get(name)) for name in FILE_OPTIONS if spec.get(name)}
    return [spec, files, len(scans)]


def code_fingerprint(obj) -> str:
    """A hash of the source of ``obj``'s module and of every dm2 module reachable from it through module-level
    names: a changed plugin, or a changed helper it uses, gives new cache keys."""
    module = inspect.getmodule(obj)
    return _module_closure_hash(module.__name__) if module is not None else ""


def module_closure(name: str) -> set[str]:
    """The dm2 modules reachable from module ``name`` through its module-level names (itself included)."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        current = todo.pop()
        if current in seen or current not in sys.modules:
            continue
        seen.add(current)
        for value in vars(sys.modules[current]).values():
            ref = value.__name__ if isinstance(value, types.ModuleType) else getattr(value, "__module__", None)
            if isinstance(ref, str) and ref.startswith("dm2_backend") and ref not in seen:
                todo.append(ref)
    return seen


@functools.cache
def _module_closure_hash(name: str) -> str:
    h = hashlib.sha1()
    for mod in sorted(module_closure(name)):
        source = getattr(sys.modules[mod], "__file__", None)
        if source and source.endswith(".py"):
            h.update(mod.encode() + b"\0" + Path(source).read_bytes())
    return h.hexdigest()[:16]
