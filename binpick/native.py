"""Native libraries that write to the process's standard output (V-HACD's progress, the UR IK
solver's notes on the solutions it drops): their lines are not the caller's output."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Iterator

_LOCK = threading.Lock()


@contextlib.contextmanager
def stdout_silenced() -> Iterator[None]:
    """The process's file descriptor 1 sent to /dev/null for the block. Serialised, so that two
    threads do not restore each other's."""
    with _LOCK:
        sys.stdout.flush()
        saved = os.dup(1)
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            os.close(devnull)
