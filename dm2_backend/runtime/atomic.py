"""Write outputs under a temporary name and rename, so a crash never leaves half a file.

Nothing here removes what it did not create: an existing folder is never replaced (a file target that is a
folder, or a folder target that exists, is an :class:`InputError`), and only our own temporaries
(``.tmp-PID-name``) are deleted: on every exit path of the writer, and, for writers killed before they could
(a dead PID), by the next write into the same folder. A full disk (or a file size limit) is an
:class:`InputError` naming the folder, with the temporary removed.

A run folder watches the writes (:func:`watching_writes`): each target is announced before it is written, so
the folder can list it in its marker first, or refuse a name that is the user's, and reported with its finished
temporary just before that is renamed into place, so the folder records what the name will hold before it holds it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from dm2_backend.runtime.errors import InputError

_TEMP = re.compile(r"\.tmp-(\d+)-")
#: called with each target path before it is written (see :func:`watching_writes`)
_watchers: list[Callable[[Path], None]] = []
#: called with each target path and its finished temporary, just before the rename
_finished: list[Callable[[Path, Path], None]] = []
#: errors that mean the device (or the size limit of this process) has no room for the write
NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def is_temporary(name: str) -> bool:
    """Whether ``name`` is one of the ``.tmp-PID-`` temporaries written here."""
    return _TEMP.match(name) is not None


@contextlib.contextmanager
def watching_writes(announce: Callable[[Path], None],
                    done: Callable[[Path, Path], None] | None = None) -> Iterator[None]:
    """Call ``announce(path)`` before each write of this process meanwhile (it may refuse: raise), and
    ``done(path, temporary)`` once the file or folder is written under its temporary name, just before the rename
    puts it in place (so whatever ends the process next, what the name holds was recorded first)."""
    _watchers.append(announce)
    if done is not None:
        _finished.append(done)
    try:
        yield
    finally:
        _watchers.remove(announce)
        if done is not None:
            _finished.remove(done)


def _placing(path: Path, temporary: Path) -> None:
    for done in list(_finished):
        done(path, temporary)


def no_space_error(exc: BaseException, path: Path) -> InputError | None:
    """The one-line error for a write of ``path`` that ran out of room (``ENOSPC``, a quota, the file size
    limit), else None."""
    if not isinstance(exc, OSError) or exc.errno not in NO_SPACE:
        return None
    why = "file size limit reached" if exc.errno == errno.EFBIG else "no space left on the device"
    return InputError(path.parent, f"{why} (writing {path.name}); nothing half-written was left")


def _temp_name(path: Path) -> Path:
    return path.with_name(f".tmp-{os.getpid()}-{path.name}")


def temp_prefix() -> str:
    """Prefix for other temporaries of this process (``tempfile`` names) that :func:`clean_stale` knows."""
    return f".tmp-{os.getpid()}-"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (owned by someone else) or cannot tell: keep its files
    return True


def clean_stale(folder: str | Path, names: tuple[str, ...] | None = None) -> list[Path]:
    """Remove ``.tmp-PID-*`` entries of ``folder`` left by processes that no longer run; returns them.
    ``names``: only the temporaries of these outputs (``.tmp-PID-<name>``, the set-aside ``.tmp-PID-old-<name>``
    and the work folders ``.tmp-PID-<name>-work-*``), what a writer of them leaves; None: every one (a folder only
    dm2 writes into, the cache)."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = _TEMP.match(entry.name)
        if m is None or _alive(int(m.group(1))):
            continue
        rest = entry.name[m.end():]
        if names is not None and not any(rest in (n, f"old-{n}") or rest.startswith(f"{n}-work-") for n in names):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _prepare(path: Path, folder: bool, replaceable: Callable[[Path], bool] | None = None) -> None:
    """Create the parent folder; refuse targets that would replace a folder (or, for a folder, a file)
    unless ``replaceable(path)`` says the folder is one this writer writes (e.g. a bag folder)."""
    if path.is_dir() and not (folder and replaceable is not None and replaceable(path)):
        what = "folder" if folder else "file"
        raise InputError(path, f"is an existing folder; dm2 does not replace folders (writing a {what} here "
                               f"would lose what it holds): remove it or choose another name")
    if folder and path.exists() and not path.is_dir():
        raise InputError(path, "is an existing file; a bag folder would replace it: remove it or choose another name")
    for announce in list(_watchers):
        announce(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise InputError(path, "cannot create the output's folder: a parent is a file") from None
    except PermissionError as exc:
        raise InputError(path, f"cannot create the output's folder ({exc.strerror})") from None
    except OSError as exc:
        if (error := no_space_error(exc, path)) is not None:
            raise error from None
        raise
    clean_stale(path.parent, (path.name,))


def _put(tmp: Path, path: Path, existed: bool) -> None:
    """Rename the file ``tmp`` to ``path``. A name that was not there when the write began (``existed``) is taken
    with a hard link, which fails if it appeared meanwhile (another program's file is never replaced); where the
    file system has no hard links, and for a name that was there (checked as replaceable before the write), by
    rename."""
    if not existed:
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise InputError(path, "appeared while it was written (not dm2's): left as it is") from None
        except OSError as exc:
            if exc.errno not in _NO_LINKS:
                raise
        else:
            os.unlink(tmp)
            return
    os.replace(tmp, path)


def _present(path: Path) -> bool:
    return path.exists() or path.is_symlink()


#: errors that mean the file system makes no hard links
_NO_LINKS = (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS)


def _remove(tmp: Path) -> None:
    if tmp.is_dir() and not tmp.is_symlink():
        shutil.rmtree(tmp, ignore_errors=True)
    elif tmp.exists() or tmp.is_symlink():
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open ``path``'s temporary twin for writing; on success rename it over ``path`` (an existing file is
    replaced, an existing folder is an :class:`InputError`)."""
    path = Path(path)
    _prepare(path, folder=False)
    existed = _present(path)
    tmp = _temp_name(path)
    try:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
        _placing(path, tmp)
        _put(tmp, path, existed)
    except OSError as exc:
        if (error := no_space_error(exc, path)) is not None:
            raise error from None
        raise
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(
    path: str | Path, folder: bool = False, replaceable: Callable[[Path], bool] | None = None
) -> Iterator[Path]:
    """Yield a temporary path for a writer that wants a name (a file, or with ``folder`` a folder); rename it
    to ``path`` on success. ``path`` must not be an existing folder, except (with ``folder``) one for which
    ``replaceable`` is true, such as an earlier output of the same writer: nothing else the user had is
    removed."""
    path = Path(path)
    _prepare(path, folder=folder, replaceable=replaceable)
    existed = _present(path)
    tmp = _temp_name(path)
    old = path.with_name(f".tmp-{os.getpid()}-old-{path.name}")
    try:
        yield tmp
        _placing(path, tmp)
        if tmp.is_dir():
            if path.is_dir() and replaceable is not None and replaceable(path):
                os.rename(path, old)  # set aside, removed once the new one is in place
            elif path.exists():  # appeared meanwhile: never replace it
                raise InputError(path, "appeared while it was written; left as it is")
            os.rename(tmp, path)
        else:
            _put(tmp, path, existed)
    except OSError as exc:
        if (error := no_space_error(exc, path)) is not None:
            raise error from None
        raise
    finally:
        _remove(tmp)
        _remove(old)
