"""Benchmarks behind `binpick bench ...`: each measures one stage's targets and returns a JSON-able
dict. Speed targets live here, never in timed tests."""

from __future__ import annotations

import os
import platform
import socket
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def machine() -> dict[str, object]:
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)),  # 1 under `taskset -c 0`
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_model": cpu_model(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a service started by a benchmark or a test)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# The parts every benchmark runs unless told otherwise: the built-in part and the shared CAD parts.
BENCH_PARTS = ("t_joint", "ipa_gear_shaft", "ipa_ring_screw", "zju_three_way_pipe")


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo; elsewhere what platform says). Timings hold
    for one CPU model: the same code ran 30-60 % slower on a 2-core AMD EPYC than on the 2-core
    Intel Xeon before it."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def timed(fn: Callable[[], object], repeats: int) -> tuple[list[float], object]:
    """Run fn `repeats` times; seconds of each run and the last result."""
    seconds, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        seconds.append(time.perf_counter() - t0)
    return seconds, result


def summary(seconds: list[float], prefix: str, scale: float = 1.0) -> dict[str, float]:
    a = np.asarray(seconds) * scale
    return {
        f"{prefix}_median": float(np.median(a)),
        f"{prefix}_p90": float(np.percentile(a, 90)),
        f"{prefix}_min": float(a.min()),
    }
