"""Processes that die with the run that started them (Linux; elsewhere these do nothing).

After `kill -9` of `dvc repro`, its stage would go on with PPID 1 and could write outputs DVC never
records; a killed stage's pool workers would live on. `die_with_parent` asks the kernel for
SIGTERM when the parent goes; `watch_ancestor` polls an ancestor further up (DVC runs stages
through a shell, which outlives DVC) and sends this process SIGTERM when it is gone.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from pathlib import Path

import psutil

log = logging.getLogger(__name__)
_PR_SET_PDEATHSIG = 1


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists (one we may not signal counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def die_with_parent() -> None:
    """SIGTERM to this process when its parent exits (prctl PR_SET_PDEATHSIG)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:  # the parent was already gone before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)


def _argv(pid: int) -> list[str]:
    try:
        return psutil.Process(pid).cmdline()
    except psutil.Error:
        return []


def is_program(argv: list[str], program: str) -> bool:
    """argv runs `program`: as the executable or its script (`.../bin/dvc`), or as `-m program`."""
    return any(Path(a).name == program for a in argv[:2]) or any(
        a == "-m" and b == program for a, b in zip(argv, argv[1:], strict=False)
    )


def _parent(pid: int) -> int:
    try:
        return psutil.Process(pid).ppid()
    except psutil.Error:
        return 0


def find_ancestor(program: str) -> int | None:
    """The nearest ancestor process running `program` (see is_program)."""
    pid = os.getppid()
    for _ in range(16):
        if pid <= 1:
            return None
        if is_program(_argv(pid), program):
            return pid
        pid = _parent(pid)
    return None


def watch_ancestor(pid: int, interval_s: float = 1.0) -> threading.Thread:
    """Send this process SIGTERM once process `pid` is gone (a daemon thread polling it)."""
    me = os.getpid()
    start_time = _start_time(pid)

    def poll() -> None:
        stop = threading.Event()
        while not stop.wait(interval_s):
            if _start_time(pid) != start_time:  # gone, or its pid reused by another process
                log.error("the run that started this stage (pid %d) is gone; stopping", pid)
                os.kill(me, signal.SIGTERM)
                return

    thread = threading.Thread(target=poll, name="watch-ancestor", daemon=True)
    thread.start()
    return thread


def _start_time(pid: int) -> float | None:
    try:
        return psutil.Process(pid).create_time()
    except psutil.Error:
        return None
