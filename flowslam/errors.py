"""Errors that flowslam reports to the user as one line (exit code 2)."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: a missing/unreadable/malformed file or an impossible option.

    The CLI prints ``str(error)`` as one line and exits with code 2 (a traceback
    only with ``--debug``). Always name the offending file and the problem, e.g.
    ``InputError(path, "size 1000 bytes is not a multiple of 16 (truncated .bin?)")``.
    """

    def __init__(self, where: str | Path | None, problem: str):
        self.where = _one_line(str(where)) if where is not None else None
        self.problem = _one_line(problem)
        super().__init__(f"{self.where}: {self.problem}" if self.where else self.problem)


def _one_line(text: str) -> str:
    """``text`` with its line breaks (e.g. inside a library's exception message) shown as `` / ``."""
    parts = text.splitlines()
    return text if parts == [text] else " / ".join(p.strip() for p in parts if p.strip())
