"""Logging set-up shared by the CLI, the stages and the flows."""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def setup_logging(verbose: bool = False) -> None:
    """Log to stderr, INFO by default; quiet the chattiest third-party loggers."""
    level = logging.DEBUG if verbose else logging.INFO
    root = logging.getLogger()
    if not any(getattr(h, "_binpick", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(_FORMAT, datefmt="%H:%M:%S"))
        handler._binpick = True  # type: ignore[attr-defined]
        root.addHandler(handler)
    root.setLevel(level)
    for name in ("trimesh", "matplotlib", "PIL", "urllib3", "alembic", "numba", "httpx", "mlflow"):
        logging.getLogger(name).setLevel(logging.WARNING)


@contextlib.contextmanager
def loggers_raised(names: tuple[str, ...], level: int) -> Iterator[None]:
    """The named loggers set to at least `level` for the block (a library's noise about what it
    handles on its own), each put back as it was after."""
    loggers = [logging.getLogger(name) for name in names]
    before = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(max(level, lg.level))
    try:
        yield
    finally:
        for lg, was in zip(loggers, before, strict=True):
            lg.setLevel(was)
