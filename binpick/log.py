"""Logging set-up shared by the CLI, the stages and the flows."""

from __future__ import annotations

import logging
import sys

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
