"""The one rule for output folders, shared by ``refine``, ``baseline``, ``simulate`` and ``demo``.

- An existing non-empty folder is refused in one line unless ``--force`` (or ``--resume`` for a refine).
- ``--force`` removes the files a previous dm2 run listed in its marker (``.dm2-run.json``) and nothing else.
- A run holds a lock on the folder while it writes; a second run into it gets one line and exit 2.
- ``--resume`` needs the folder's checkpoint and the same inputs, config and seed; what differs is named.
- A run that fails removes what it created; an interrupted one keeps its checkpoint for ``--resume``.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from dm2_backend.errors import InputError

MARKER = ".dm2-run.json"
LOCK = ".dm2-lock"
CHECKPOINT = "checkpoint.pt"
#: config keys a resume may change: how long and where to run, not what is optimised
RESUMABLE = {"optimiser.epochs", "optimiser.max_steps", "device", "nproc"}
#: the order in which differing inputs are named
INPUT_ORDER = ["command", "scans", "frames", "poses", "poses_content"]


@dataclass
class RunFolder:
    """An output folder held by this process; :meth:`record` lists what the run wrote in the marker."""

    path: Path
    command: str
    fingerprint: dict = field(default_factory=dict)
    created: bool = False
    before: frozenset[str] = frozenset()
    #: files of the run a resume continues (kept in the marker)
    inherited: tuple[str, ...] = ()
    _lock: object | None = None

    def record(self, files: list[str] | None = None) -> None:
        """Write the marker: the command, its fingerprint and every file now in the folder that was not
        there before (what ``--force`` may remove later)."""
        if files is None:
            files = sorted((set(_entries(self.path)) - self.before - {LOCK, MARKER}) | set(self.inherited))
        _write_marker(self.path, {"command": self.command, "fingerprint": self.fingerprint, "files": files})

    def discard(self) -> None:
        """Remove what this run created (the folder itself if it made it)."""
        if self.created:
            shutil.rmtree(self.path, ignore_errors=True)
            return
        for name in set(_entries(self.path)) - self.before - {LOCK}:
            _remove(self.path / name)

    def release(self) -> None:
        if self._lock is not None:
            (self.path / LOCK).unlink(missing_ok=True)
            self._lock.close()
            self._lock = None


def fingerprint(cfg: dict, **inputs) -> dict:
    """What a resume must share with the run it continues: the config (flattened) and the inputs."""
    return {"config": _flatten(cfg), "inputs": {k: str(v) for k, v in inputs.items() if v is not None}}


def check_target(out: Path) -> None:
    """``out`` can be a folder we write: not a file, no file among its parents."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    for parent in out.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(out, f"cannot create: {parent} is a file, not a folder")
            if not os.access(parent, os.W_OK | os.X_OK) and not out.exists():
                raise InputError(out, f"cannot create: {parent} is not writable")
            break


def open_folder(out: Path, command: str, *, force: bool = False, resume: bool = False,
                fp: dict | None = None) -> RunFolder:
    """Check, lock and (with ``force``) clear ``out`` before any long work; see the module docstring."""
    out = Path(out)
    check_target(out)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out, f"cannot create the folder: {exc.strerror}") from exc
    folder = RunFolder(out, command, fp or {}, created)
    folder._lock = _take_lock(out)
    try:
        previous = _read_marker(out)
        if resume:
            _check_resume(out, previous, folder.fingerprint)
            folder.inherited = tuple(previous.get("files", []))
        elif _entries(out) - {LOCK}:
            if not force:
                raise InputError(out, "folder is not empty: give --force to replace a previous run's files"
                                      + (", or --resume to continue it" if command == "refine" else ""))
            if previous is not None:  # a killed run may not have listed its checkpoint
                for name in [*previous.get("files", []), CHECKPOINT, MARKER]:
                    _remove(out / name)
        folder.before = frozenset(_entries(out))
        folder.record(files=list(folder.inherited))  # from now on a killed run can be resumed or replaced
    except BaseException:
        folder.release()
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return folder


@contextlib.contextmanager
def run_folder(out: Path, command: str, *, force: bool = False, resume: bool = False,
               fp: dict | None = None) -> Iterator[RunFolder]:
    """:func:`open_folder` for the duration of a run: on success the marker is written; on an error what the
    run created is removed; on Ctrl-C the folder is kept (its checkpoint serves ``--resume``)."""
    folder = open_folder(out, command, force=force, resume=resume, fp=fp)
    try:
        yield folder
        folder.record()
    except KeyboardInterrupt:
        folder.record()
        raise
    except BaseException:
        folder.discard()
        raise
    finally:
        folder.release()


@contextlib.contextmanager
def adding_to(out: Path) -> Iterator[None]:
    """Write more files into a finished run folder (``dm2 map``, ``dm2 view``): the folder is locked meanwhile,
    and the files that appear are added to its marker, so a later ``--force`` replaces them with the rest."""
    out = Path(out)
    lock = _take_lock(out)
    before = _entries(out)
    try:
        yield
    finally:
        previous = _read_marker(out)
        if previous is not None:
            new = _entries(out) - before - {LOCK, MARKER}
            _write_marker(out, {**previous, "files": sorted(set(previous.get("files", [])) | new)})
        (out / LOCK).unlink(missing_ok=True)
        lock.close()


def _take_lock(out: Path):
    try:
        fh = open(out / LOCK, "a+")  # noqa: SIM115 (held until release)
    except OSError as exc:
        raise InputError(out, f"cannot write in this folder: {exc.strerror}") from exc
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.seek(0)
        holder = fh.read().strip() or "?"
        fh.close()
        raise InputError(out, f"another dm2 run (pid {holder}) is writing this folder") from exc
    fh.seek(0)
    fh.truncate()
    fh.write(str(os.getpid()))
    fh.flush()
    return fh


def _check_resume(out: Path, previous: dict | None, fp: dict) -> None:
    if not (out / CHECKPOINT).exists():
        raise InputError(out, f"--resume: no {CHECKPOINT} here to continue from (run without --resume)")
    if previous is None:
        raise InputError(out, f"--resume: no {MARKER} here, so the inputs and config of the checkpoint are unknown")
    diff = _differences(previous.get("fingerprint", {}), fp)
    if diff:
        raise InputError(out, "--resume: the checkpoint was made with different " + "; ".join(diff))


def _differences(old: dict, new: dict) -> list[str]:
    out = []
    for section in ("inputs", "config"):
        a, b = old.get(section, {}), new.get(section, {})
        keys = sorted((k for k in set(a) | set(b) if a.get(k) != b.get(k) and k not in RESUMABLE),
                      key=lambda k: (INPUT_ORDER.index(k) if k in INPUT_ORDER else len(INPUT_ORDER), k))
        out += [f"{k} ({_short(a.get(k, '-'))} then, {_short(b.get(k, '-'))} now)" for k in keys[:2]]
        if len(keys) > 2:
            out.append(f"{len(keys) - 2} more {section} keys")
    return out


def _short(value) -> str:
    text = str(value)
    return Path(text).name if "/" in text else text


def _flatten(d: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten(v, key + "."))
        else:
            flat[key] = v if isinstance(v, (int, float, str, bool, type(None))) else str(v)
    return flat


def digest(path: Path | None) -> str | None:
    """A short content digest of a small input file (size and first MiB), None for none."""
    if path is None or not Path(path).is_file():
        return None
    h = hashlib.sha1()
    with open(path, "rb") as fh:
        h.update(fh.read(1 << 20))
    return f"{Path(path).stat().st_size}:{h.hexdigest()[:12]}"


def _write_marker(out: Path, doc: dict) -> None:
    tmp = out / f".tmp-{os.getpid()}-{MARKER}"
    tmp.write_text(json.dumps(doc, indent=2, default=str))
    os.replace(tmp, out / MARKER)


def _read_marker(out: Path) -> dict | None:
    try:
        return json.loads((out / MARKER).read_text())
    except (OSError, ValueError):
        return None


def _entries(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()} if out.is_dir() else set()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
