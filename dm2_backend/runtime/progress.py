"""Progress of the long stages, by one rule: a tqdm bar only when stderr is a terminal.

Anywhere else (a file, a pipe, CI) no bar is drawn, so a log holds no carriage-return redraws; instead each
stage ends with one ``logging`` line (INFO, logger ``dm2_backend.runtime.progress``) with its count, its time and
its last status, e.g. ``loop closure: 120/120 in 4.2 s (closures=7)``. On a terminal the bar disappears
when the stage ends and the same line stays. Status updates (:meth:`Progress.set_postfix`) never force a
redraw: the bar shows them at its next regular refresh (at most every :data:`MININTERVAL` seconds).

``dm2``'s command line shows these lines (and every warning) on stderr through :func:`setup_logging`.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from tqdm import tqdm

log = logging.getLogger(__name__)

#: seconds between two redraws of a bar
MININTERVAL = 0.5


def is_terminal(stream: TextIO | None = None) -> bool:
    """Whether ``stream`` (default: the current ``sys.stderr``) is an interactive terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # closed or foreign stream objects
        return False


class Progress:
    """An iterable over ``iterable`` that reports the stage ``desc``: a bar on a terminal, else one line."""

    def __init__(self, iterable: Iterable, desc: str, total: int | None = None, unit: str = "it",
                 enabled: bool = True, stream: TextIO | None = None) -> None:
        self.iterable, self.desc, self.unit, self.enabled = iterable, desc, unit, enabled
        if total is None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.total = total
        self.postfix: dict[str, Any] = {}
        self.count = 0
        self._stream = stream
        self._bar: tqdm | None = None

    def __len__(self) -> int:
        return self.total if self.total is not None else 0

    def set_postfix(self, **values: Any) -> None:
        """The stage's status (shown on the bar at its next refresh, and in the final line)."""
        self.postfix = values
        if self._bar is not None:
            self._bar.set_postfix(values, refresh=False)

    def __iter__(self) -> Iterator:
        stream = sys.stderr if self._stream is None else self._stream
        if self.enabled and is_terminal(stream):
            from tqdm import tqdm  # only where a bar is drawn (the command line starts faster without it)

            self._bar = tqdm(total=self.total, desc=self.desc, unit=self.unit, leave=False, file=stream,
                             mininterval=MININTERVAL, dynamic_ncols=True)
        t0 = time.perf_counter()
        try:
            for item in self.iterable:
                yield item
                self.count += 1
                if self._bar is not None:
                    self._bar.update(1)
        finally:
            if self._bar is not None:
                self._bar.close()
                self._bar = None
            if self.enabled:
                log.info("%s", self.summary(time.perf_counter() - t0))

    def summary(self, seconds: float) -> str:
        """``desc: count[/total] in S s[ (status)]``."""
        done = f"{self.count}/{self.total}" if self.total is not None else str(self.count)
        status = ", ".join(f"{k}={_short(v)}" for k, v in self.postfix.items())
        return f"{self.desc}: {done} in {seconds:.1f} s" + (f" ({status})" if status else "")


def _short(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def progress(iterable: Iterable, desc: str, *, total: int | None = None, unit: str = "it", enabled: bool = True,
             stream: TextIO | None = None) -> Progress:
    """Iterate ``iterable`` as the stage ``desc`` (see the module's rule); ``enabled=False``: silent."""
    return Progress(iterable, desc, total, unit, enabled, stream)


class _StderrHandler(logging.StreamHandler):
    """Writes to the ``sys.stderr`` of the moment (click's test runner and pytest swap it)."""

    def __init__(self) -> None:
        super().__init__()

    @property  # type: ignore[override]
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, value: TextIO) -> None:  # StreamHandler.__init__ assigns it
        pass


class _Format(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        return f"dm2: {text}" if record.levelno < logging.WARNING else f"dm2: {record.levelname.lower()}: {text}"


_HANDLER: _StderrHandler | None = None


def setup_logging(level: int = logging.INFO) -> None:
    """Show dm2's log (stage lines and warnings) on stderr, one line each; idempotent."""
    global _HANDLER
    logger = logging.getLogger("dm2_backend")
    if _HANDLER is None:
        _HANDLER = _StderrHandler()
        _HANDLER.setFormatter(_Format())
    if _HANDLER not in logger.handlers:
        logger.addHandler(_HANDLER)
    logger.setLevel(level)
