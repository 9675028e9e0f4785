"""PLY point clouds read in Python/numpy (no C reader sees the file): ``ascii``, ``binary_little_endian``
and ``binary_big_endian``; the ``vertex`` element's scalar properties come back as columns.

The header is checked before anything is allocated: its size, the element counts against the bytes the
file holds, known property types, names that are text. Elements before ``vertex`` are skipped (lists
included); elements after it are not read. Every problem is an :class:`InputError` naming the file
(and the header line).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2_backend.runtime.errors import InputError

#: PLY scalar type names -> numpy type codes
TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 16
MAX_TOKEN = 256


@dataclass
class Element:
    name: str
    count: int
    #: (name, type code) of scalar properties, or (name, (count type, item type)) of lists
    properties: list[tuple[str, str | tuple[str, str]]]
    line: int


def _header(data: bytes, path: Path) -> tuple[str, list[Element], int]:
    """(format, elements, offset of the body)."""
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        what = "no 'ply' magic" if not data.startswith(b"ply") else f"no end_header in {MAX_HEADER_BYTES} bytes"
        raise InputError(path, f"not a PLY file ({what})")
    nl = data.find(b"\n", end)
    body = len(data) if nl < 0 else nl + 1
    try:
        text = data[:end].decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"PLY header is not ASCII text (byte {exc.start})") from None
    fmt = None
    elements: list[Element] = []
    for no, raw in enumerate(text.replace("\r", "").split("\n"), 1):
        tokens = raw.split()
        if not tokens or tokens[0] in ("comment", "obj_info", "ply"):
            continue
        if any(len(t) > MAX_TOKEN for t in tokens):
            raise InputError(path, f"PLY header token longer than {MAX_TOKEN} characters", line=no)
        key = tokens[0]
        if key == "format":
            if len(tokens) != 3 or tokens[1] not in FORMATS:
                raise InputError(path, f"unknown PLY format {' '.join(tokens[1:])!r}", line=no)
            fmt = tokens[1]
        elif key == "element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise InputError(path, f"bad element line {raw.strip()!r}", line=no)
            elements.append(Element(tokens[1], int(tokens[2]), [], no))
        elif key == "property":
            if not elements:
                raise InputError(path, "property before any element", line=no)
            if len(tokens) == 3 and tokens[1] in TYPES:
                elements[-1].properties.append((tokens[2], TYPES[tokens[1]]))
            elif len(tokens) == 5 and tokens[1] == "list" and tokens[2] in TYPES and tokens[3] in TYPES:
                elements[-1].properties.append((tokens[4], (TYPES[tokens[2]], TYPES[tokens[3]])))
            else:
                raise InputError(path, f"bad property line {raw.strip()!r}", line=no)
        else:
            raise InputError(path, f"unknown PLY header keyword {key!r}", line=no)
    if fmt is None:
        raise InputError(path, "PLY header has no format line")
    return fmt, elements, body


def _scalar_dtype(element: Element, order: str) -> np.dtype | None:
    if any(not isinstance(t, str) for _, t in element.properties):
        return None
    names = [n for n, _ in element.properties]
    if len(set(names)) != len(names):
        raise InputError(None, f"element {element.name!r} repeats a property name")
    return np.dtype([(n, order + t) for n, t in element.properties])


def _skip_binary_lists(data: bytes, pos: int, element: Element, order: str, path: Path) -> int:
    """Offset after ``element`` (which has list properties) in binary data, walking it item by item."""
    limit = len(data)
    for _ in range(element.count):
        for _, t in element.properties:
            if isinstance(t, str):
                pos += np.dtype(t).itemsize
                continue
            size = np.dtype(t[0]).itemsize
            if pos + size > limit:
                raise InputError(path, f"truncated PLY data in element {element.name!r}")
            n = int(np.frombuffer(data, order + t[0], 1, pos)[0])
            if n < 0:
                raise InputError(path, f"negative list length in element {element.name!r}")
            pos += size + n * np.dtype(t[1]).itemsize
        if pos > limit:
            raise InputError(path, f"truncated PLY data in element {element.name!r}")
    return pos


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """The ``vertex`` element's scalar properties of a PLY file, name -> (N,) array."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except IsADirectoryError:
        raise InputError(path, "is a folder, expected a PLY file") from None
    fmt, elements, pos = _header(data, path)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError(path, "PLY file has no vertex element")
    order = FORMATS[fmt]
    lines = data[pos:].split(b"\n") if order is None else None
    line = 0
    for element in elements:
        try:
            dtype = _scalar_dtype(element, order or "<")
        except InputError as exc:
            raise InputError(path, exc.problem, line=element.line) from None
        if element.name != "vertex":
            if order is None:
                line += element.count
                if line > len(lines):
                    raise InputError(path, f"truncated PLY data in element {element.name!r}")
            elif dtype is None:
                pos = _skip_binary_lists(data, pos, element, order, path)
            else:
                pos += element.count * dtype.itemsize
            continue
        if dtype is None:
            raise InputError(path, "PLY vertex element has a list property (not a point cloud)", line=element.line)
        if dtype.itemsize == 0:
            raise InputError(path, "PLY vertex element has no properties", line=element.line)
        if order is None:
            return _ascii_vertices(path, lines[line:], element, dtype)
        need = element.count * dtype.itemsize
        if pos + need > len(data):
            raise InputError(path, f"truncated PLY data: {element.count} vertices need {need} bytes, "
                                   f"{max(len(data) - pos, 0)} remain")
        rec = np.frombuffer(data, dtype, element.count, pos)
        return {n: rec[n].astype(rec[n].dtype.newbyteorder("=")) for n in dtype.names}
    raise AssertionError("unreachable: vertex element checked above")


def _ascii_vertices(path: Path, lines: list[bytes], element: Element, dtype: np.dtype) -> dict[str, np.ndarray]:
    width = len(dtype.names)
    if element.count > len(lines):
        raise InputError(path, f"truncated PLY data: {element.count} vertices declared, {len(lines)} lines follow")
    rows = [ln.split() for ln in lines[: element.count]]
    bad = next((k for k, r in enumerate(rows) if len(r) != width), None)
    if bad is not None:
        raise InputError(path, f"vertex {bad} has {len(rows[bad])} values, expected {width}")
    try:
        table = np.array(rows, dtype=np.float64).reshape(-1, width)
    except ValueError:
        raise InputError(path, "vertex data is not all numbers") from None
    out = {}
    for k, name in enumerate(dtype.names):
        kind = dtype[name].kind
        col = table[:, k]
        if kind in "iu":
            info = np.iinfo(dtype[name])
            if not (np.isfinite(col).all() and (col >= info.min).all() and (col <= info.max).all()):
                raise InputError(path, f"property {name!r}: value outside its integer type")
        out[name] = col.astype(dtype[name].newbyteorder("="))
    return out
