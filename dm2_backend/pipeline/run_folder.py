"""The one rule for output folders, shared by ``refine``, ``baseline``, ``simulate`` and ``demo``.

- An existing non-empty folder is refused in one line unless ``--force`` (or ``--resume`` for a refine).
- ``--force`` removes the files a previous dm2 run listed in its marker (``.dm2-run.json``) and nothing else,
  and of those only the ones that still hold what that run wrote there (:mod:`~dm2_backend.pipeline.ownership`:
  size and digest of every file, recorded as each is put in place). The marker is input: it may list only plain
  names of entries inside the folder (no ``/``, ``..``, absolute paths); one that lists anything else is refused
  whole, and nothing is removed.
- The marker lists each output before it is written (through :mod:`dm2_backend.runtime.atomic`), so a run killed at
  any point leaves a marker that names everything it wrote, and records its identity once it is in place. What
  other programs write into the folder meanwhile is not the run's: never listed, never removed.
- A file that no dm2 run listed (yours), or that changed since a run wrote it, is never replaced, even with
  ``--force``: a run that would write one of its names is refused in one line before any work, and at the write
  itself.
- A run holds a lock on the folder while it writes; a second run into it gets one line and exit 2.
- ``--resume`` needs the folder's checkpoint and the same inputs, config and seed; what differs is named.
- A run that fails removes what it wrote (and the folder, if it made it and nothing else is in it); an
  interrupted one (Ctrl-C, SIGTERM, SIGHUP) keeps its checkpoint for ``--resume``, or, without one (interrupted
  in preparation), removes what it wrote like a failed run, so that the same command is accepted again
  (finished preparation steps come from the cache).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import fnmatch
import hashlib
import json
import os
import shutil
import stat
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from dm2_backend.config.schema import RunConfig
from dm2_backend.optim.dense_checkpoint import DENSE_CHECKPOINT
from dm2_backend.pipeline.ownership import Written, identity, relative_in, still_ours
from dm2_backend.runtime.atomic import is_temporary, watching_writes
from dm2_backend.runtime.errors import InputError

MARKER = ".dm2-run.json"
LOCK = ".dm2-lock"
CHECKPOINT = "checkpoint.pt"
#: what ``--resume`` continues from: the optimiser's checkpoint, the dense stage's
CHECKPOINTS = (CHECKPOINT, DENSE_CHECKPOINT)
#: config keys a resume may change: how long and where to run, not what is optimised
RESUMABLE = {"optimiser.epochs", "optimiser.max_steps", "device", "nproc"}
#: the order in which differing inputs are named
INPUT_ORDER = ["command", "scans", "frames", "poses", "poses_content"]
#: top-level names that dm2 runs write (refine, baseline, simulate, demo, map, view): a file of yours with one of
#: these names in --out is refused before any work, since the run would replace it
OUTPUT_NAMES = ("config.yaml", "resolved.yaml", "report.json", "warm_start.*", "topology.*", "trajectory.png",
                "errors.png", "epochs.png", "consistency.*", "map.*", "mnet*", "octomap.bt", "maps.json", "prior",
                *CHECKPOINTS, "poses*", "*_lidar_*", "graph.g2o", "velodyne", "times.txt", "info.json", "README.txt",
                "*.rrd", "hba")
#: a marker larger than this is not one dm2 wrote
MARKER_MAX_BYTES = 32 << 20


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, SIGTERM or SIGHUP during a run: ``next_step`` says what to run next."""

    def __init__(self, next_step: str, resume: bool) -> None:
        super().__init__(next_step)
        self.next_step = next_step
        self.resume = resume


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
    #: names this run announced before writing them (see :meth:`announce`)
    written: set[str] = field(default_factory=set)
    #: the identities the marker held for the inherited files
    inherited_identity: dict[str, str] = field(default_factory=dict)
    #: what this run put in place, by content
    content: Written = field(init=False)
    _lock: object | None = None
    _remove_folder: bool = False

    def __post_init__(self) -> None:
        self.content = Written(self.path)

    @property
    def users(self) -> frozenset[str]:
        """Entries that were here before the run and that are not the run's it continues: never replaced."""
        return _users(self.before - set(self.inherited))

    def record(self, files: list[str] | None = None) -> None:
        """Write the marker: the command, its fingerprint, every file of this run (what ``--force`` may remove
        later: those it announced and those of the run it resumes) and the identity of each that is in place."""
        if files is None:
            files = sorted(self.written | set(self.inherited))
        known = {**self.inherited_identity, **self.content.identities()}
        _write_marker(self.path, {"command": self.command, "fingerprint": self.fingerprint, "files": files,
                                  "identity": {name: known[name] for name in files if name in known}})

    def placed(self, path: Path, temporary: Path) -> None:
        """Called by :mod:`dm2_backend.runtime.atomic` just before ``temporary`` is renamed to ``path``: what the
        name will hold is recorded, in the marker at once for a top-level entry; a folder written file by file is
        recorded whole with the next name listed and when the run ends (killed in between, its writing was cut
        short: left for you to remove)."""
        name = self.content.placed(path, temporary)
        if name is not None and name in self.content.whole:
            self.record()

    def announce(self, path: Path) -> None:
        """Called by :mod:`dm2_backend.runtime.atomic` before it writes ``path``: a path inside this folder is listed in
        the marker first (a run killed while writing still names it); one that would replace a file of the
        user's, or one another program put there meanwhile, is refused."""
        rel = relative_in(self.path, path)
        if rel is None:
            return  # not in this folder (the cache, another output)
        name = rel.parts[0]
        if name in self.users:
            raise InputError(self.path / name, _NOT_OURS)
        target = self.path / rel
        if (target.exists() or target.is_symlink()) and not self._may_replace(rel):
            raise InputError(target, _APPEARED)
        if name not in self.written and name not in self.inherited:
            self.written.add(name)
            self.record(sorted(self.written | set(self.inherited)))

    def _may_replace(self, rel: Path) -> bool:
        """Whether the existing ``rel`` is this run's, or the run's it continues, and still holds what was written."""
        name = rel.parts[0]
        if len(rel.parts) > 1 and (name in self.content.whole or name in self.inherited):
            return True  # inside a folder checked as a whole when it was placed or inherited
        if self.content.recorded(rel) is not None:
            return still_ours(self.path / rel, self.content.recorded(rel))
        if len(rel.parts) == 1 and name in self.inherited:
            return name not in self.inherited_identity or still_ours(self.path / name, self.inherited_identity[name])
        return False

    def discard(self) -> None:
        """Remove what this run wrote and still holds what it wrote (and the folder itself, once released, if it
        made it and nothing else is there): never what other programs put there meanwhile."""
        known = self.content.identities()
        for name in sorted(self.written - self.before):
            if still_ours(self.path / name, known.get(name)):
                _remove(self.path / name)
            elif name in self.content.parts:
                _remove_parts(self.path / name, self.content.parts_of(name))
        if MARKER not in self.before:  # the marker this run started
            _remove(self.path / MARKER)
        self._remove_folder = self.created

    def release(self) -> None:
        if self._lock is not None:
            (self.path / LOCK).unlink(missing_ok=True)
            self._lock.close()
            self._lock = None
        if self._remove_folder:
            with contextlib.suppress(OSError):  # only while empty
                self.path.rmdir()


def refuse_overlap(out: Path, inputs: dict[str, Path | None]) -> None:
    """``--out`` may not be ``/`` or the home folder, be an input, hold one (``--force`` would remove it) or lie
    inside an input folder (or the cache); resolved through links. ``inputs``: option name -> path (None: not
    given)."""
    where = Path(os.path.realpath(out))
    if where == Path("/") or where == Path(os.path.realpath(Path.home())):
        raise InputError(out, "is the root or home folder: give a folder of its own for the run")
    for name, path in inputs.items():
        if path is None:
            continue
        given = Path(os.path.realpath(path))
        if given == where or where in given.parents:
            raise InputError(out, f"holds the input {name} {path}: write the run elsewhere (--force would remove "
                                  "what dm2 wrote there)")
        if given.is_dir() and given in where.parents:
            raise InputError(out, f"lies inside the input {name} folder {path}: write the run elsewhere")


def fingerprint(cfg: RunConfig, **inputs) -> dict:
    """What a resume must share with the run it continues: the config (flattened) and the inputs."""
    return {"config": _flatten(cfg.model_dump()), "inputs": {k: str(v) for k, v in inputs.items() if v is not None}}


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
    try:
        folder._lock = _take_lock(out)
    except InputError:
        if created:  # rmdir: only while empty (a concurrent run that holds the folder has its lock in it)
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    try:
        previous = _read_marker(out)
        listed = _listed_names(out, previous)
        recorded = _recorded(out, previous)
        ours = [name for name in listed if still_ours(out / name, recorded.get(name))]
        changed = [name for name in listed if name not in ours and _present(out / name)]
        if resume:
            _check_resume(out, previous, folder.fingerprint)
            # the checkpoints are judged by their content when read (``pipeline.refine.check_checkpoints``)
            checkpoints = [name for name in CHECKPOINTS if (out / name).is_file() and not (out / name).is_symlink()]
            folder.inherited = tuple(sorted({*ours, *checkpoints}))
            folder.inherited_identity = {name: recorded[name] for name in ours if name in recorded}
        elif _occupied(out, listed):
            if not force:
                raise InputError(out, "folder is not empty: give --force to replace a previous run's files"
                                      + (", or --resume to continue it" if command == "refine" else ""))
            _check_no_collision(out, _users(_entries(out) - set(ours)), changed)  # before anything is removed
            for name in ours:
                _remove(out / name)
            if previous is not None:
                _remove(out / MARKER)
        folder.before = frozenset(_entries(out))
        _check_no_collision(out, folder.users, changed)
        folder.record(files=list(folder.inherited))  # from now on a killed run can be resumed or replaced
    except BaseException:
        folder.release()
        if created:  # only the marker this run started can be in it
            _remove(out / MARKER)
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    return folder


@contextlib.contextmanager
def run_folder(out: Path, command: str, *, force: bool = False, resume: bool = False,
               fp: dict | None = None) -> Iterator[RunFolder]:
    """:func:`open_folder` for the duration of a run: on success the marker is written; on an error what the
    run created is removed; on Ctrl-C the folder is kept (its checkpoint serves ``--resume``)."""
    folder = open_folder(out, command, force=force, resume=resume, fp=fp)
    try:
        with watching_writes(folder.announce, folder.placed):
            yield folder
        folder.record()
    except KeyboardInterrupt as exc:
        if any((folder.path / name).is_file() for name in CHECKPOINTS):
            folder.record()
            raise Interrupted(f"{folder.path} keeps the checkpoint: add --resume to the same command to "
                              "continue from it", resume=True) from exc
        folder.discard()
        raise Interrupted(f"nothing was kept in {folder.path}: run the same command again (finished "
                          "preparation steps come from the cache)", resume=False) from exc
    except BaseException:
        folder.discard()
        raise
    finally:
        folder.release()


@contextlib.contextmanager
def adding_to(out: Path) -> Iterator[None]:
    """Write more files into a finished run folder (``dm2 map``, ``dm2 view``): the folder is locked meanwhile,
    only what a dm2 run wrote there and still holds what it wrote may be replaced, and each file written is added
    to its marker with its identity as it is put in place, so a later ``--force`` replaces it with the rest."""
    out = Path(out)
    lock = _take_lock(out)
    content = Written(out)
    try:
        marker = _read_marker(out)
        listed = _listed_names(out, marker)
        recorded = _recorded(out, marker)
        ours = {name for name in listed if still_ours(out / name, recorded.get(name))}
        users = _users(_entries(out) - ours)

        def refuse(path: Path) -> None:
            rel = relative_in(out, path)
            if rel is None:
                return
            name = rel.parts[0]
            if name in users:
                why = _CHANGED if name in listed else _NOT_OURS
                raise InputError(out / name, why.replace("choose another --out", "remove it first"))
            target = out / rel
            if _present(target) and name not in ours and not still_ours(target, content.recorded(rel)):
                raise InputError(target, _APPEARED)

        def placed(path: Path, temporary: Path) -> None:
            if content.placed(path, temporary) is not None and marker is not None:
                names = sorted({*listed, *content.whole, *content.parts})
                known = {**recorded, **content.identities()}
                _write_marker(out, {**marker, "files": names, "identity": {n: known[n] for n in names if n in known}})

        with watching_writes(refuse, placed):
            yield
    finally:
        (out / LOCK).unlink(missing_ok=True)
        lock.close()


_NOT_OURS = ("is not listed in this folder's .dm2-run.json (not a dm2 run's output), and this run writes a file of "
             "that name: dm2 never replaces your files, even with --force; move it or choose another --out")
_CHANGED = ("was listed by a dm2 run but no longer holds what it wrote (changed since, its writing cut short, or "
            "listed by a dm2 that did not record what it wrote), and this run writes a file of that name: dm2 leaves "
            "it as it is, even with --force; move it or choose another --out")
_APPEARED = ("appeared while this run wrote into the folder (another program's): dm2 leaves it as it is; move it and "
             "run again")


def _users(entries: set[str] | frozenset[str]) -> frozenset[str]:
    """The entries that are not dm2's lock, marker or temporaries."""
    return frozenset(name for name in entries - {LOCK, MARKER} if not is_temporary(name))


def _present(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def _check_no_collision(out: Path, users: frozenset[str], changed: Collection[str] = ()) -> None:
    """Before any work: a file of the user's (or one changed since dm2 wrote it) that has the name of a dm2 output
    is refused, not replaced."""
    clash = sorted(name for name in users if any(fnmatch.fnmatchcase(name, p) for p in OUTPUT_NAMES))
    if clash:
        raise InputError(out / clash[0], _CHANGED if clash[0] in changed else _NOT_OURS)


def _remove_parts(folder: Path, parts: dict[str, str | None]) -> None:
    """Remove the files of ``folder`` that still hold what this run wrote, then its folders left empty."""
    for rel, ident in parts.items():
        if still_ours(folder / rel, ident):
            _remove(folder / rel)
    for root, dirs, _ in sorted(os.walk(folder, topdown=False), key=lambda w: -len(w[0])):
        for name in dirs:
            with contextlib.suppress(OSError):
                os.rmdir(os.path.join(root, name))
    with contextlib.suppress(OSError):
        folder.rmdir()


def _occupied(out: Path, listed: list[str]) -> bool:
    """Whether ``out`` holds anything besides our lock, a marker that lists nothing there (a run killed before
    it wrote anything) and the temporaries of dead dm2 processes."""
    rest = {name for name in _entries(out) - {LOCK} if not is_temporary(name)}
    if rest == {MARKER} and not any((out / name).exists() or (out / name).is_symlink() for name in listed):
        return False
    return bool(rest)


def _listed_names(out: Path, marker: dict | None) -> list[str]:
    """The ``files`` of a marker, each checked to be a plain name inside ``out``; a marker that lists
    anything else was not written by dm2 and is refused whole (before anything is removed)."""
    if marker is None:
        return []
    files = marker.get("files", [])
    if not isinstance(files, list):
        raise InputError(out / MARKER, "not a dm2 run marker ('files' is not a list); nothing was removed")
    for name in files:
        if not _plain_name(name):
            raise InputError(out / MARKER, f"lists {_short_repr(name)}, which is not a plain name inside the "
                                           "folder: dm2 never writes such a marker; nothing was removed (remove "
                                           "the marker, or the folder, yourself)")
    return list(files)


def adopt_unrecorded(out: Path, command: str) -> None:
    """For a folder that is dm2's own (the demo's default): a marker of ``command`` written by a dm2 that recorded no
    identities gets those of the entries it lists, as they are now (never through a link), so that ``--force``
    replaces them. Anything else is left as it is."""
    marker = _read_marker(out) if out.is_dir() else None
    if marker is None or "identity" in marker or marker.get("command") != command:
        return
    names = _listed_names(out, marker)
    known = {name: ident for name in names if (ident := _identity_or_none(out / name)) is not None}
    _write_marker(out, {**marker, "identity": known})


def _identity_or_none(path: Path) -> str | None:
    try:
        return identity(path)
    except OSError:
        return None


def _recorded(out: Path, marker: dict | None) -> dict[str, str]:
    """The ``identity`` of a marker (name -> recorded identity). A marker without one (crafted, or written by a dm2
    that did not record identities) owns nothing: a name alone never gets a file removed. One whose identities are
    not plain names and short strings was not written by dm2 and is refused whole."""
    if marker is None:
        return {}
    ids = marker.get("identity", {})
    if not isinstance(ids, dict) or not all(_plain_name(k) and isinstance(v, str) and len(v) <= 64
                                            for k, v in ids.items()):
        raise InputError(out / MARKER, "not a dm2 run marker ('identity' is not a table of names and digests); "
                                       "nothing was removed")
    return dict(ids)


def _plain_name(name) -> bool:
    return (isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name
            and "\0" not in name and name not in (LOCK, MARKER) and len(name) <= 255)


def _short_repr(value, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _take_lock(out: Path):
    """The folder's lock, held until release: a plain file opened without following a link (a link or a FIFO
    named like the lock is refused, nothing written through it)."""
    flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(out / LOCK, flags, 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(out / LOCK, "is a link, not a lock dm2 made: remove it or write elsewhere") from None
        raise InputError(out, f"cannot write in this folder: {exc.strerror}") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise InputError(out / LOCK, "is not a plain file, not a lock dm2 made: remove it or write elsewhere")
    fh = os.fdopen(fd, "r+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.seek(0)
        holder = fh.read().strip() or "?"
        fh.close()
        raise InputError(out, f"another dm2 run (pid {holder}) is writing this folder") from exc
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
    except OSError as exc:
        with contextlib.suppress(OSError):  # closing flushes the same unwritten bytes again
            fh.close()
        (out / LOCK).unlink(missing_ok=True)
        raise InputError(out, f"cannot write in this folder: {_no_space(exc)}") from None
    return fh


def _no_space(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "no space left on the device"
    return exc.strerror or str(exc)


def _check_resume(out: Path, previous: dict | None, fp: dict) -> None:
    if not any((out / name).exists() for name in CHECKPOINTS):
        raise InputError(out, f"--resume: no {CHECKPOINT} or {DENSE_CHECKPOINT} here to continue from (run "
                              "without --resume)")
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
    try:
        tmp.write_text(json.dumps(doc, indent=2, default=str))
        os.replace(tmp, out / MARKER)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise InputError(out, f"cannot write {MARKER}: {_no_space(exc)}") from None


def _read_marker(out: Path) -> dict | None:
    """The marker of ``out`` (a regular file of bounded size holding a JSON object), or None."""
    path = out / MARKER
    try:
        if not path.is_file() or path.is_symlink() or path.stat().st_size > MARKER_MAX_BYTES:
            return None
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _entries(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()} if out.is_dir() else set()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
