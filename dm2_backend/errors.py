"""Errors that the CLI turns into one line and exit code 2."""

from __future__ import annotations

from pathlib import Path


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

    @property
    def message(self) -> str:
        where = self.source or ""
        if self.line is not None:
            where += f":{self.line}"
        if self.topic is not None:
            where += f" [topic {self.topic}]"
        return f"{where}: {self.problem}" if where else self.problem
