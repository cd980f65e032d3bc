"""Errors a user can act on.

Every error the pipeline raises on bad input is a :class:`PipelineError`: the CLI prints it as one
line (what went wrong, the file, and the fix) and exits non-zero; ``--debug`` adds the traceback.
"""

from __future__ import annotations

from pathlib import Path

# the first fix for a disk that is (or would get) full: what frees disk without losing the run
FREE_DISK = "free disk space (`sgpor-pipeline clean OUT --keep-last 1` deletes cached results the run no longer uses)"


def named(items: list[str], limit: int) -> str:
    """``items`` joined for a message, the first ``limit`` of them and ", ..." when there are more."""
    return ", ".join(items[:limit]) + (", ..." if len(items) > limit else "")


class PipelineError(Exception):
    """An error with the file it concerns and what the user can do about it."""

    def __init__(self, message: str, path: str | Path | None = None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.fix = fix
        super().__init__(self.one_line())

    def one_line(self) -> str:
        text = self.message
        if self.path:
            text = f"{self.path}: {text}"
        if self.fix:
            text = f"{text} (fix: {self.fix})"
        return text


class LockedError(PipelineError):
    """Another run holds the output folder."""


class NonFiniteError(PipelineError):
    """NaN or inf found in a tensor or parameter."""
