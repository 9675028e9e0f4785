"""Plain text tables: one cell's text and an aligned table (the terminal, Markdown and ``dm2 compare``)."""

from __future__ import annotations

import math


def fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool) or isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.6f}" if abs(v) < 1e6 else f"{v:.6g}"
    return str(v)


def format_table(header: list[str], body: list[list]) -> str:
    """Plain aligned text table (numbers right-aligned)."""
    cells = [[fmt(c) for c in r] for r in body]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    numeric = [all(isinstance(r[i], (int, float)) or r[i] is None for r in body) for i in range(len(header))]

    def line(items: list[str]) -> str:
        cols = zip(items, widths, numeric, strict=True)
        return "  ".join(s.rjust(w) if num else s.ljust(w) for s, w, num in cols).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in cells)])
