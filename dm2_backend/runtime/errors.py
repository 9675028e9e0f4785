"""Errors that the CLI turns into one line and exit code 2."""

from __future__ import annotations

import difflib
import re
from pathlib import Path

_BREAKS = re.compile(r"\s*[\r\n]+\s*")
#: longest error line: a value quoted in a message is cut, not echoed whole (a 50 MB argument)
MAX_LINE = 1000


def one_line(text: str) -> str:
    """``text`` with its line breaks (and the blanks around them) collapsed to one space, at most
    :data:`MAX_LINE` characters (a longer one is cut in the middle)."""
    text = _BREAKS.sub(" ", text).strip()
    if len(text) > MAX_LINE:
        cut = len(text) - MAX_LINE
        text = f"{text[: MAX_LINE // 2]} [... {cut} characters ...] {text[-MAX_LINE // 2 :]}"
    return text


class InputError(Exception):
    """Bad user input: names the file (and line or topic) and what is wrong."""

    def __init__(
        self,
        source: str | Path | None,
        problem: str,
        *,
        line: int | None = None,
        topic: str | None = None,
    ) -> None:
        self.source = str(source) if source is not None else None
        self.problem = problem
        self.line = line
        self.topic = topic
        super().__init__(self.message)

    def __reduce__(self):
        """Pickled with its parts (raised in a task on another process, it arrives whole)."""
        return (type(self), (self.source, self.problem), {"line": self.line, "topic": self.topic})

    @property
    def message(self) -> str:
        where = self.source or ""
        if self.line is not None:
            where += f":{self.line}"
        if self.topic is not None:
            where += f" [topic {self.topic}]"
        text = f"{where}: {self.problem}" if where else self.problem
        return one_line(text)  # third-party messages (YAML, rosbags) span lines; the CLI promises one


def did_you_mean(name: str, choices) -> str:
    """``" (did you mean 'epochs'?)"`` for the closest of ``choices`` to a mistyped ``name``, else ``""``."""
    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""
