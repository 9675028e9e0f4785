"""Loading ``.npy`` / ``.npz`` files a user hands in, without pickles and without trusting their headers.

The header (format version, dtype, shape, order) is parsed first; the dtype must be numeric (or a structured
dtype of numeric scalar fields) and the data size it declares must fit in the bytes the file (or the zip
member) holds, so a header declaring terabytes is refused before anything is allocated. Objects are never
unpickled. Every problem is an :class:`InputError` naming the file.
"""

from __future__ import annotations

import math
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from dm2_backend.runtime.errors import InputError

#: largest array accepted from one .npy file or .npz member (bytes)
MAX_ARRAY_BYTES = 2 << 30
#: an .npz member may expand to this multiple of its compressed size (or 64 MiB): a bound on zip bombs
MAX_RATIO, RATIO_FLOOR = 1000, 64 << 20
#: largest header numpy itself accepts by default
MAX_HEADER = 10_000
_HEADER_ERRORS = (ValueError, EOFError, OSError, SyntaxError, tokenize.TokenError, OverflowError, TypeError,
                  KeyError, zlib.error, zipfile.BadZipFile)


def _dtype_problem(dtype: np.dtype) -> str | None:
    if dtype.names is None:
        if dtype.kind in "biuf" and dtype.subdtype is None:
            return None
        return f"dtype {dtype.str} is not a numeric type"
    for name in dtype.names:
        sub = dtype.fields[name][0]
        if sub.names is not None or sub.subdtype is not None or sub.kind not in "biuf":
            return f"field {name!r} has dtype {sub.str}, not a numeric scalar"
    return None


def read_header(fh: BinaryIO, source: str | Path) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` of the .npy header at ``fh``'s position; :class:`InputError` for
    anything but a well-formed header of a numeric dtype."""
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh, max_header_size=MAX_HEADER)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh, max_header_size=MAX_HEADER)
        else:
            raise InputError(source, f"unsupported .npy format version {version[0]}.{version[1]}")
    except _HEADER_ERRORS as exc:
        raise InputError(source, f"not a readable .npy array (bad header: {exc or type(exc).__name__})") from None
    if not all(isinstance(n, int) and n >= 0 for n in shape):
        raise InputError(source, f"bad .npy shape {shape}")
    problem = _dtype_problem(dtype)
    if problem is not None:
        raise InputError(source, f"not a readable .npy array: {problem} (dm2 reads numeric arrays only; objects "
                                 "are never unpickled)")
    return tuple(shape), bool(fortran), dtype


def _read_body(fh: BinaryIO, source, shape, fortran, dtype: np.dtype, available: int) -> np.ndarray:
    count = math.prod(shape)
    need = count * dtype.itemsize
    if need > MAX_ARRAY_BYTES:
        raise InputError(source, f"the .npy header declares {need} bytes of data (limit {MAX_ARRAY_BYTES})")
    if need > available:
        raise InputError(source, f"truncated .npy data: the header declares {need} bytes, {available} follow it")
    try:
        data = fh.read(need)
    except (OSError, EOFError, zlib.error, zipfile.BadZipFile) as exc:
        raise InputError(source, f"cannot read the array data ({exc})") from None
    if len(data) < need:
        raise InputError(source, f"truncated .npy data: {len(data)} of {need} bytes")
    array = np.frombuffer(data, dtype=dtype, count=count)
    return array.reshape(shape, order="F" if fortran else "C").copy()


def load_npy(path: str | Path) -> np.ndarray:
    """A numeric array from a .npy file (checked header, no pickles)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            shape, fortran, dtype = read_header(fh, path)
            return _read_body(fh, path, shape, fortran, dtype, size - fh.tell())
    except IsADirectoryError:
        raise InputError(path, "is a folder, expected a .npy file") from None
    except FileNotFoundError:
        raise InputError(path, "no such file") from None


def load_numeric_npy(path: str | Path) -> np.ndarray:
    """A user's ``.npy`` file as a numeric array (:func:`load_npy`'s checks); :class:`InputError` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file" if not path.exists() else "is not a file")
    array = load_npy(path)  # checked header and size, never a pickle
    if array.dtype.kind not in "iuf":
        raise InputError(path, "not a numeric .npy array")
    return array


def npy_shape(path: str | Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype from a .npy header, without reading the data."""
    path = Path(path)
    with open(path, "rb") as fh:
        shape, _, dtype = read_header(fh, path)
    return shape, dtype


#: largest total a .npz may declare (sum of its members' uncompressed sizes)
MAX_NPZ_BYTES = 2 << 30


def sniff_shape(path: Path, accept) -> bool:
    """Whether ``path`` is an ``.npy`` file whose header declares a numeric array of a shape ``accept`` takes
    (only the header is read)."""
    if not path.is_file() or path.suffix.lower() != ".npy":
        return False
    try:
        shape, dtype = npy_shape(path)
    except InputError:
        return False
    return dtype.kind in "iuf" and bool(accept(shape))


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of an .npz file (name without ``.npy`` -> array); checked headers, sizes, no pickles."""
    path = Path(path)
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as exc:  # zipfile's errors
        raise InputError(path, f"not a readable .npz (zip) file: {exc}") from None
    out: dict[str, np.ndarray] = {}
    with zf:
        infos = zf.infolist()
        total = sum(i.file_size for i in infos)
        if total > MAX_NPZ_BYTES:
            raise InputError(path, f"the .npz declares {total} bytes uncompressed (limit {MAX_NPZ_BYTES})")
        for info in infos:
            name = info.filename
            key = name[:-4] if name.endswith(".npy") else name
            where = f"{path} [{name}]"
            if info.file_size > max(RATIO_FLOOR, MAX_RATIO * info.compress_size):
                raise InputError(path, f"member {name!r} declares {info.file_size} bytes from {info.compress_size} "
                                       f"compressed (more than {MAX_RATIO}x: refused as a zip bomb)")
            try:
                with zf.open(info) as fh:
                    shape, fortran, dtype = read_header(fh, where)
                    header = fh.tell()
                    out[key] = _read_body(fh, where, shape, fortran, dtype, info.file_size - header)
            except InputError as exc:
                raise InputError(path, f"member {name!r}: {exc.problem}") from None
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error, ValueError, NotImplementedError,
                    RuntimeError) as exc:  # corrupt / unsupported / encrypted members (zipfile's own errors)
                raise InputError(path, f"member {name!r} cannot be read: {exc}") from None
    return out
