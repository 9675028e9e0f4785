"""Files read from disk are input: a regular file (or a folder where one is expected) of bounded size.

A FIFO would block the read forever and ``/dev/zero`` would never end it, so anything that is not a regular
file or a folder is refused by its type before it is opened, and text is read with a size bound.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from dm2_backend.runtime.errors import InputError

#: bounds per kind of file (bytes): a config is a few lines; a trajectory of 10 million poses fits in 1 GiB
CONFIG_MAX_BYTES = 4 << 20
TEXT_MAX_BYTES = 1 << 30

_KINDS = {stat.S_ISFIFO: "a FIFO (named pipe)", stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device",
          stat.S_ISSOCK: "a socket"}


def check_kind(path: str | Path, folder_ok: bool = True) -> os.stat_result | None:
    """The ``stat`` of ``path`` when it is a regular file (or, with ``folder_ok``, a folder); None when it does
    not exist; :class:`InputError` for a FIFO, a device, a socket or a symlink loop."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:  # ELOOP, ENAMETOOLONG, EACCES on a parent ...
        raise InputError(path, exc.strerror or str(exc)) from None
    if stat.S_ISREG(st.st_mode) or (folder_ok and stat.S_ISDIR(st.st_mode)):
        return st
    if stat.S_ISDIR(st.st_mode):
        raise InputError(path, "is a folder, expected a file")
    kind = next((name for test, name in _KINDS.items() if test(st.st_mode)), "not a regular file")
    raise InputError(path, f"is {kind}, not a regular file: dm2 reads only regular files")


def read_text_bounded(path: str | Path, limit: int = TEXT_MAX_BYTES, what: str = "text file") -> str:
    """The UTF-8 text of a regular file of at most ``limit`` bytes; one-line errors for anything else."""
    st = check_kind(path, folder_ok=False)
    if st is None:
        raise InputError(path, "no such file")
    if st.st_size > limit:
        raise InputError(path, f"{st.st_size} bytes, larger than any {what} dm2 reads ({limit >> 20} MiB)")
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)  # the file may grow after the stat
    except OSError as exc:
        raise InputError(path, exc.strerror or str(exc)) from None
    if len(data) > limit:
        raise InputError(path, f"larger than any {what} dm2 reads ({limit >> 20} MiB)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
