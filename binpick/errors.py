"""Errors a user can act on.

A `BinpickError` carries a one-line message that names the file (or setting) and the problem.
Entry points print that line and exit non-zero instead of showing a traceback.
"""

from __future__ import annotations

from pathlib import Path


class BinpickError(Exception):
    """An error caused by input or settings, not by a bug: reported as one line."""


class InputError(BinpickError):
    """A file that cannot be used: missing, wrong format, wrong content."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class ParamsError(BinpickError):
    """A settings file that does not validate."""


class NothingAboveTheFloor(BinpickError):
    """Cleaning left (almost) nothing above the support plane and inside the walls: an empty bin,
    or a capture of something else."""


class MissingDependencyError(BinpickError):
    """An optional package is needed for this action and is not installed."""
