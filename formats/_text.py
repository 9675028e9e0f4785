"""Shared helpers of the text trajectory formats: numeric tables with line numbers, exact float text,
validation that names the file line."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dm2_backend.kernel.trajectory import Trajectory, validate_poses, validate_timestamps
from dm2_backend.runtime.errors import InputError
from dm2_backend.runtime.input_files import TEXT_MAX_BYTES, check_kind

log = logging.getLogger(__name__)

#: Largest accepted deviation of a parsed quaternion's norm from 1 (print rounding is far smaller;
#: a larger one means a wrong column or a broken file).
QUAT_NORM_TOL = 1e-2


def open_text(path: Path) -> list[str]:
    """All lines of a text file; :class:`InputError` for a missing, unreadable, binary or oversized file, or
    for something that is not a regular file (a FIFO, a device)."""
    st = check_kind(path)
    if st is None:
        raise InputError(path, "no such file")
    if Path(path).is_dir():
        raise InputError(path, "is a folder, expected a text file")
    if st.st_size > TEXT_MAX_BYTES:
        raise InputError(path, f"{st.st_size} bytes, larger than any trajectory text dm2 reads "
                               f"({TEXT_MAX_BYTES >> 20} MiB)")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not a text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise InputError(path, exc.strerror or str(exc)) from None


def data_lines(lines: list[str], comment: str = "#") -> Iterator[tuple[int, list[str]]]:
    """(1-based line number, fields) of each non-blank, non-comment line; commas count as spaces."""
    for number, text in enumerate(lines, start=1):
        text = text.strip()
        if not text or text.startswith(comment):
            continue
        fields = text.replace(",", " ").split()
        if fields:  # a line of commas only is blank
            yield number, fields


def parse_floats(path: Path, number: int, fields: list[str]) -> list[float]:
    """Floats of one line; :class:`InputError` naming the line for text or NaN/inf."""
    try:
        values = [float(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not is_float(f))
        raise InputError(path, f"not a number: {bad!r}", line=number) from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(path, "NaN or infinite value", line=number)
    return values


def is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_table(
    path: Path, columns: tuple[int, ...], what: str, comment: str = "#"
) -> tuple[np.ndarray, np.ndarray]:
    """Numeric rows (N, C) float64 and their line numbers (N,); every row must have the column count
    of the first one, which must be one of ``columns``."""
    rows: list[list[str]] = []
    numbers: list[int] = []
    width = None
    for number, fields in data_lines(open_text(path), comment):
        if width is None:
            if len(fields) not in columns:
                raise InputError(path, count_problem(len(fields), columns, what), line=number)
            width = len(fields)
        elif len(fields) != width:
            raise InputError(path, count_problem(len(fields), (width,), what), line=number)
        rows.append(fields)
        numbers.append(number)
    if not rows:
        raise InputError(path, f"no {what} lines (empty file?)")
    return to_floats(path, rows, numbers), np.asarray(numbers)


def to_floats(path: Path, rows: list[list[str]], numbers: list[int]) -> np.ndarray:
    """Rows of number strings (equal lengths) to float64, naming the line of text or NaN/inf."""
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:
        for number, fields in zip(numbers, rows, strict=True):
            parse_floats(path, number, fields)
        raise
    finite = np.isfinite(data).all(axis=1)
    if not finite.all():
        raise InputError(path, "NaN or infinite value", line=numbers[int(np.argmax(~finite))])
    return data


def count_problem(got: int, expected: tuple[int, ...], what: str) -> str:
    want = " or ".join(str(c) for c in expected)
    return f"{got} columns, expected {want} ({what})"


def check_quaternions(path: Path, q: np.ndarray, lines: np.ndarray) -> None:
    """:class:`InputError` naming the line of a quaternion whose norm is far from 1."""
    with np.errstate(over="ignore", invalid="ignore"):  # a huge entry: an inf norm, refused below
        norms = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(norms - 1.0) <= QUAT_NORM_TOL)
    if bad.any():
        i = int(np.argmax(bad))
        norm = float(norms[i])
        raise InputError(path, f"quaternion norm {norm:.4g} is not 1 (not a rotation)", line=int(lines[i]))


def validate(traj: Trajectory, path: Path, lines: np.ndarray, duplicates_ok: bool = False) -> Trajectory:
    """Validate poses and timestamps (repeated ones allowed with ``duplicates_ok``), naming the file line of
    the first bad row."""
    try:
        validate_poses(traj.poses, path, 0)
        if traj.timestamps is not None:
            validate_timestamps(traj.timestamps, path, 0, duplicates_ok)
    except InputError as exc:
        line = None if exc.line is None else int(lines[exc.line])
        raise InputError(path, exc.problem, line=line) from None
    return traj


def drop_duplicate_times(
    stamps: np.ndarray, rows: np.ndarray, lines: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Keep the first of each run of equal consecutive timestamps; also returns the dropped lines."""
    keep = np.ones(len(stamps), bool)
    keep[1:] = np.diff(stamps) != 0
    return stamps[keep], rows[keep], lines[keep], [int(n) for n in lines[~keep]]


#: what a text trajectory reader does with a repeated timestamp (``ReadOptions.duplicate_times``):
#: "keep" every pose, as evo's readers do (the default; one warning), "keep-first" of each run, or "error"
DUPLICATE_POLICIES = ("keep", "keep-first", "error")


def duplicate_policy(options) -> str:
    """``ReadOptions.duplicate_times``, one of :data:`DUPLICATE_POLICIES` ("keep" by default)."""
    policy = getattr(options, "duplicate_times", "keep")
    if policy not in DUPLICATE_POLICIES:
        raise ValueError(f"duplicate_times must be one of {', '.join(DUPLICATE_POLICIES)}, not {policy!r}")
    return policy


def duplicate_times(
    path: Path, stamps: np.ndarray, rows: np.ndarray, lines: np.ndarray, options, meta: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Apply the :func:`duplicate_policy` to repeated consecutive timestamps: "keep" keeps every pose as evo
    does (its association then picks the nearest pose, as for any other stamp) with one warning and the
    repeating lines in ``meta["duplicate_lines"]``; "keep-first" drops the later poses of a run (their lines
    in ``meta["dropped_duplicate_lines"]``). Returns the rows and whether repeated stamps may remain."""
    policy = duplicate_policy(options)
    if policy == "keep-first":
        stamps, rows, lines, dropped = drop_duplicate_times(stamps, rows, lines)
        if dropped:
            meta["dropped_duplicate_lines"] = dropped
    elif policy == "keep":
        repeated = np.flatnonzero(np.diff(stamps) == 0) + 1
        if len(repeated):
            meta["duplicate_lines"] = [int(n) for n in lines[repeated]]
            i = int(repeated[0])
            more = f" and {len(repeated) - 1} more" if len(repeated) > 1 else ""
            log.warning("%s: line %d repeats the timestamp %r of line %d%s; kept every pose, as evo does",
                        path, int(lines[i]), float(stamps[i]), int(lines[i - 1]), more)
    return stamps, rows, lines, policy == "keep"


def fmt(value: float) -> str:
    """Shortest text that reads back as the same float64 (Python's repr)."""
    return repr(float(value))


def fmt_row(values: np.ndarray) -> str:
    return " ".join(map(repr, np.asarray(values, dtype=np.float64).tolist()))


def sniff_rows(path: Path, columns: int, max_lines: int = 20, comment: str = "#") -> np.ndarray | None:
    """The first data lines (up to ``max_lines``) as floats when all have ``columns`` numeric fields."""
    rows = []
    check_kind(path)
    with open(path, encoding="utf-8") as fh:
        for number, line in enumerate(fh):
            if number > 10 * max_lines or len(rows) >= max_lines:
                break
            text = line.strip()
            if not text or text.startswith(comment):
                continue
            fields = text.replace(",", " ").split()
            if len(fields) != columns or not all(is_float(f) for f in fields):
                return None
            rows.append([float(f) for f in fields])
    return np.asarray(rows) if rows else None


def sniff_poses(path: Path, columns: int, quaternion_from: int) -> bool:
    """Whether the file's first rows are ``columns`` numbers whose four from ``quaternion_from`` are unit
    quaternions (a pose a line)."""
    rows = sniff_rows(path, columns)
    if rows is None:
        return False
    norms = np.linalg.norm(rows[:, quaternion_from:quaternion_from + 4], axis=1)
    return bool(np.all(np.abs(norms - 1) < QUAT_NORM_TOL))
