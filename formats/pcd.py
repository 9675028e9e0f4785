"""PCD (Point Cloud Library) files: header parser, reader and writer for ``ascii``, ``binary`` and
``binary_compressed`` data, any fields, sizes, types and counts, organised or not.

Fields come back as ``name -> array`` ((N,) when COUNT is 1, else (N, COUNT)) in file order; PCL's
padding fields named ``_`` are skipped. LZF (used by ``binary_compressed``) is implemented here in
pure Python: the PyPI bindings are C source distributions only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError

DATA_KINDS = ("ascii", "binary", "binary_compressed")
_TYPE_SIZES = {"F": (2, 4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_NUMPY_KIND = {"F": "f", "I": "i", "U": "u"}
#: largest COUNT of one field (PCL's own histograms use a few hundred)
MAX_COUNT = 1 << 16


@dataclass
class PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int = 1
    points: int = 0
    data: str = "binary"
    version: str = "0.7"
    viewpoint: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    #: 1-based line number of the DATA line (ascii points start on the next line)
    data_line: int = 0
    extra: dict = field(default_factory=dict)

    def field_dtype(self, i: int) -> np.dtype:
        return np.dtype(f"<{_NUMPY_KIND[self.types[i]]}{self.sizes[i]}")

    def record_dtype(self) -> np.dtype:
        """The packed dtype of one point in ``binary`` data (fields with COUNT > 1 are sub-arrays)."""
        names = [f"f{i}" for i in range(len(self.fields))]
        formats = [self.field_dtype(i) if c == 1 else (self.field_dtype(i), (c,))
                   for i, c in enumerate(self.counts)]
        return np.dtype({"names": names, "formats": formats})

    def text(self) -> str:
        """The header as written in a file (ends with the DATA line and a newline)."""
        return "".join([
            "# .PCD v0.7 - Point Cloud Data file format\n",
            f"VERSION {self.version}\n",
            "FIELDS " + " ".join(self.fields) + "\n",
            "SIZE " + " ".join(map(str, self.sizes)) + "\n",
            "TYPE " + " ".join(self.types) + "\n",
            "COUNT " + " ".join(map(str, self.counts)) + "\n",
            f"WIDTH {self.width}\nHEIGHT {self.height}\n",
            "VIEWPOINT " + " ".join(f"{v:g}" for v in self.viewpoint) + "\n",
            f"POINTS {self.points}\nDATA {self.data}\n",
        ])


def _ints(values: list[str], key: str, source, line: int) -> list[int]:
    try:
        out = [int(v) for v in values]
    except ValueError:
        raise InputError(source, f"{key} needs whole numbers, got {' '.join(values)!r}", line=line) from None
    if any(v < 0 for v in out):
        raise InputError(source, f"{key} must not be negative", line=line)
    return out


def parse_header(lines: list[str], source: str | Path | None = None) -> PcdHeader:
    """Parse header lines up to and including ``DATA``; :class:`InputError` naming the line."""
    items: dict[str, tuple[list[str], int]] = {}
    for no, raw in enumerate(lines, 1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        key = tokens[0].upper()
        items[key] = (tokens[1:], no)
        if key == "DATA":
            break
    else:
        raise InputError(source, "not a PCD file: no DATA line in the header")
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH"):
        if key not in items and not (key == "FIELDS" and "COLUMNS" in items):
            raise InputError(source, f"PCD header has no {key} line")
    names, no = items.get("FIELDS") or items["COLUMNS"]
    n = len(names)
    if n == 0:
        raise InputError(source, "PCD header lists no FIELDS", line=no)
    if len(set(f for f in names if f != "_")) != len([f for f in names if f != "_"]):
        raise InputError(source, f"PCD header repeats a field name: {' '.join(names)}", line=no)
    sizes = _ints(items["SIZE"][0], "SIZE", source, items["SIZE"][1])
    types = [t.upper() for t in items["TYPE"][0]]
    counts = _ints(items["COUNT"][0], "COUNT", source, items["COUNT"][1]) if "COUNT" in items else [1] * n
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != n:
            line = items[key][1] if key in items else None
            raise InputError(source, f"{key} has {len(values)} entries for {n} FIELDS", line=line)
    if any(c < 1 or c > MAX_COUNT for c in counts):
        raise InputError(source, f"COUNT values must be 1 to {MAX_COUNT}, got {' '.join(map(str, counts))}",
                         line=items["COUNT"][1])
    for i, (t, s) in enumerate(zip(types, sizes, strict=True)):
        if s not in _TYPE_SIZES.get(t, ()):
            raise InputError(source, f"field {names[i]!r}: unsupported TYPE {t} with SIZE {s}",
                             line=items["TYPE"][1])
    (width,) = _one_int(items, "WIDTH", source)
    (height,) = _one_int(items, "HEIGHT", source) if "HEIGHT" in items else (1,)
    (points,) = _one_int(items, "POINTS", source) if "POINTS" in items else (width * height,)
    if points != width * height:
        raise InputError(source, f"POINTS {points} is not WIDTH x HEIGHT = {width * height}", line=items.get(
            "POINTS", ([], None))[1])
    data_values, data_line = items["DATA"]
    kind = data_values[0].lower() if data_values else ""
    if kind not in DATA_KINDS:
        raise InputError(source, f"unknown DATA kind {kind!r} (expected one of {', '.join(DATA_KINDS)})",
                         line=data_line)
    header = PcdHeader(names, sizes, types, counts, width, height, points, kind, data_line=data_line)
    if "VERSION" in items and items["VERSION"][0]:
        header.version = items["VERSION"][0][0]
    if "VIEWPOINT" in items:
        vp, line = items["VIEWPOINT"]
        try:
            header.viewpoint = tuple(float(v) for v in vp)
        except ValueError:
            raise InputError(source, f"VIEWPOINT is not numeric: {' '.join(vp)!r}", line=line) from None
    return header


def _one_int(items: dict, key: str, source) -> list[int]:
    values, line = items[key]
    if len(values) != 1:
        raise InputError(source, f"{key} needs one number", line=line)
    return _ints(values, key, source, line)


def read_pcd(path: str | Path) -> tuple[PcdHeader, dict[str, np.ndarray]]:
    """Header and fields of a PCD file."""
    path = Path(path)
    with open(path, "rb") as fh:
        lines: list[str] = []
        while True:
            raw = fh.readline()
            if not raw:
                break
            try:
                lines.append(raw.decode("ascii"))
            except UnicodeDecodeError:
                raise InputError(path, "not a PCD file: the header is not text",
                                 line=len(lines) + 1) from None
            if raw.split()[:1] and raw.split()[0].upper() == b"DATA":
                break
        header = parse_header(lines, path)
        body = fh.read()
    return header, decode_body(header, body, path)


def decode_body(header: PcdHeader, body: bytes, source: str | Path | None = None) -> dict[str, np.ndarray]:
    if header.data == "ascii":
        return _decode_ascii(header, body, source)
    if header.data == "binary":
        dtype = header.record_dtype()
        need = header.points * dtype.itemsize
        if len(body) < need:
            raise InputError(source, f"truncated binary PCD data: {len(body)} bytes for "
                                     f"{header.points} points of {dtype.itemsize} bytes")
        rec = np.frombuffer(body, dtype=dtype, count=header.points)
        return {n: np.array(rec[f"f{i}"]) for i, n in enumerate(header.fields) if n != "_"}
    return _decode_compressed(header, body, source)


def _decode_compressed(header: PcdHeader, body: bytes, source) -> dict[str, np.ndarray]:
    if header.points == 0:
        return _empty(header)
    if len(body) < 8:
        raise InputError(source, "truncated binary_compressed PCD data: no size words")
    packed, unpacked = (int(v) for v in np.frombuffer(body[:8], "<u4"))
    expected = header.points * sum(s * c for s, c in zip(header.sizes, header.counts, strict=True))
    if unpacked != expected:
        raise InputError(source, f"binary_compressed PCD data declares {unpacked} bytes, the header's "
                                 f"{header.points} points need {expected}")
    if len(body) < 8 + packed:
        raise InputError(source, f"truncated binary_compressed PCD data: {len(body) - 8} of {packed} bytes")
    try:
        raw = lzf_decompress(body[8:8 + packed], unpacked)
    except ValueError as exc:
        raise InputError(source, f"corrupt binary_compressed PCD data: {exc}") from None
    out, start = {}, 0
    for i, name in enumerate(header.fields):
        dt = header.field_dtype(i)
        nbytes = header.points * header.counts[i] * dt.itemsize
        if start + nbytes > len(raw):
            raise InputError(source, f"binary_compressed PCD data too short for field {name!r}")
        arr = np.frombuffer(raw, dt, header.points * header.counts[i], start)
        start += nbytes
        if name != "_":
            arr = arr.reshape(header.points, header.counts[i]).copy()
            out[name] = arr[:, 0] if header.counts[i] == 1 else arr
    return out


def _empty(header: PcdHeader) -> dict[str, np.ndarray]:
    return {n: np.zeros((0,) if c == 1 else (0, c), header.field_dtype(i))
            for i, (n, c) in enumerate(zip(header.fields, header.counts, strict=True)) if n != "_"}


def _decode_ascii(header: PcdHeader, body: bytes, source) -> dict[str, np.ndarray]:
    total = sum(header.counts)
    rows: list[list[str]] = []
    for no, line in enumerate(body.decode("ascii", errors="replace").splitlines(), header.data_line + 1):
        tokens = line.split()
        if not tokens:
            continue
        if len(rows) == header.points:
            break
        if len(tokens) != total:
            raise InputError(source, f"expected {total} values per point, found {len(tokens)}", line=no)
        rows.append(tokens)
    if len(rows) < header.points:
        raise InputError(source, f"truncated ascii PCD data: {len(rows)} of {header.points} points")
    if not rows:
        return _empty(header)
    table = np.array(rows, dtype=str)
    out, col = {}, 0
    for i, name in enumerate(header.fields):
        cells = table[:, col:col + header.counts[i]]
        col += header.counts[i]
        if name == "_":
            continue
        dt = header.field_dtype(i)
        try:
            values = cells.astype(np.float64).astype(dt) if dt.kind == "f" else _to_int(cells, dt)
        except (ValueError, OverflowError):
            bad = next(r for r in range(len(cells)) if not _parses(cells[r], dt))
            raise InputError(source, f"field {name!r}: bad value {' '.join(cells[bad])!r} for TYPE "
                                     f"{header.types[i]}{header.sizes[i]}",
                             line=_point_line(body, header, bad)) from None
        out[name] = values[:, 0] if header.counts[i] == 1 else values
    return out


def _to_int(cells: np.ndarray, dt: np.dtype) -> np.ndarray:
    values = cells.astype(object)
    ints = np.vectorize(int, otypes=[object])(values)
    info = np.iinfo(dt)
    if ((ints < info.min) | (ints > info.max)).any():
        raise OverflowError
    return ints.astype(dt)


def _parses(cells: np.ndarray, dt: np.dtype) -> bool:
    try:
        if dt.kind == "f":
            cells.astype(np.float64)
        else:
            _to_int(cells.reshape(1, -1), dt)
        return True
    except (ValueError, OverflowError):
        return False


def _point_line(body: bytes, header: PcdHeader, point: int) -> int:
    seen = -1
    for no, line in enumerate(body.decode("ascii", errors="replace").splitlines(), header.data_line + 1):
        if line.split():
            seen += 1
            if seen == point:
                return no
    return header.data_line


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress LZF data (liblzf's format) of known uncompressed ``size``; ValueError when corrupt."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            end = i + ctrl + 1
            if end > n:
                raise ValueError("literal run past the end of the data")
            out += data[i:end]
            i = end
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                raise ValueError("back reference past the end of the data")
            length += data[i]
            i += 1
        if i >= n:
            raise ValueError("back reference past the end of the data")
        ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0:
            raise ValueError("back reference before the start of the data")
        period = len(out) - ref
        if length <= period:
            out += out[ref:ref + length]
        else:  # overlapping copy repeats the last ``period`` bytes
            out += (out[ref:] * (length // period + 1))[:length]
        if len(out) > size:
            break
    if len(out) != size:
        raise ValueError(f"decompressed to {len(out)} bytes, header says {size}")
    return bytes(out)


def lzf_compress(data: bytes) -> bytes:
    """Compress ``data`` to LZF (greedy matching on 3-byte hashes, as liblzf); pure Python, ~1 MB/s."""
    out = bytearray()
    n = len(data)
    table: dict[bytes, int] = {}
    lit = i = 0

    def literals(end: int) -> None:
        for s in range(lit, end, 32):
            chunk = data[s:min(s + 32, end)]
            out.append(len(chunk) - 1)
            out.extend(chunk)

    while i + 2 < n:
        key = data[i:i + 3]
        ref = table.get(key)
        table[key] = i
        if ref is None or i - ref > 8192:
            i += 1
            continue
        length, longest = 3, min(264, n - i)
        while length < longest and data[ref + length] == data[i + length]:
            length += 1
        literals(i)
        off, code = i - ref - 1, length - 2
        if code < 7:
            out.append((code << 5) | (off >> 8))
        else:
            out += bytes(((7 << 5) | (off >> 8), code - 7))
        out.append(off & 0xFF)
        i += length
        lit = i
    literals(n)
    return bytes(out)


_PCD_TYPE = {"f": "F", "i": "I", "u": "U", "b": "U"}


def write_pcd(
    path: str | Path,
    points: np.ndarray,
    fields: Mapping[str, np.ndarray] | None = None,
    *,
    binary: bool = True,
    compressed: bool = False,
    width: int | None = None,
    height: int = 1,
    **more_fields: np.ndarray,
) -> None:
    """Write points (N,3) and extra per-point fields ((N,) or (N,k), any numeric dtype) as a PCD file.

    ``compressed=True`` writes ``binary_compressed``; ``binary=False`` writes ``ascii``. ``width`` x
    ``height`` = N describes an organised cloud (default: unorganised, height 1).
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    columns: dict[str, np.ndarray] = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    for name, arr in {**(fields or {}), **more_fields}.items():
        arr = np.asarray(arr)
        if arr.dtype == bool:
            arr = arr.astype(np.uint8)
        if arr.shape[0] != len(pts) or arr.ndim > 2 or arr.dtype.kind not in "fiu":
            raise ValueError(f"field {name!r}: need a numeric (N,) or (N,k) array for N = {len(pts)} points")
        columns[name] = arr
    w = len(pts) if width is None else width
    if w * height != len(pts):
        raise ValueError(f"width {w} x height {height} is not the {len(pts)} points")
    header = PcdHeader(
        fields=list(columns),
        sizes=[a.dtype.itemsize for a in columns.values()],
        types=[_PCD_TYPE[a.dtype.kind] for a in columns.values()],
        counts=[1 if a.ndim == 1 else a.shape[1] for a in columns.values()],
        width=w, height=height, points=len(pts),
        data="binary_compressed" if compressed else "binary" if binary else "ascii",
    )
    with atomic_write(path, "wb") as fh:
        fh.write(header.text().encode("ascii"))
        fh.write(encode_body(header, list(columns.values())))


def encode_body(header: PcdHeader, columns: list[np.ndarray]) -> bytes:
    cols = [np.ascontiguousarray(c, dtype=header.field_dtype(i)).reshape(header.points, -1)
            for i, c in enumerate(columns)]
    if header.data == "ascii":
        fmt = []
        for i, c in enumerate(cols):
            f = ("%.9g" if header.sizes[i] == 4 else "%.17g") if header.types[i] == "F" else "%d"
            fmt += [f] * c.shape[1]
        table = np.empty((header.points, len(fmt)), dtype=object)
        j = 0
        for c in cols:
            for k in range(c.shape[1]):
                table[:, j] = c[:, k].tolist()
                j += 1
        line = " ".join(fmt) + "\n"
        return "".join(line % tuple(row) for row in table).encode("ascii")
    if header.data == "binary":
        rec = np.empty(header.points, header.record_dtype())
        for i, c in enumerate(cols):
            rec[f"f{i}"] = c if header.counts[i] != 1 else c[:, 0]
        return rec.tobytes()
    raw = b"".join(c.tobytes() for c in cols)
    packed = lzf_compress(raw) if raw else b""
    return np.array([len(packed), len(raw)], "<u4").tobytes() + packed
