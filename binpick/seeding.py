"""Seeds derived from the params' seed and names, so that every part, split and scene has its
own reproducible stream, independent of the order or the number of workers."""

from __future__ import annotations

import zlib

import numpy as np


def derive_seed(seed: int, *names: str | int) -> np.random.SeedSequence:
    """A SeedSequence from the base seed and a path of names (strings hashed with CRC-32)."""
    words = [int(seed)] + [zlib.crc32(n.encode()) if isinstance(n, str) else int(n) for n in names]
    return np.random.SeedSequence(words)


def derive_int(seed: int, *names: str | int) -> int:
    """A 31-bit integer seed (for libraries that take an int) derived like derive_seed."""
    return int(derive_seed(seed, *names).generate_state(1)[0] & 0x7FFFFFFF)
