"""Seeds derived from the params' seed and names, so that every part, split and scene has its
own reproducible stream, independent of the order or the number of workers."""

from __future__ import annotations

import hashlib
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Every DIGEST_STRIDE-th value of a capture is hashed: the digest must be the same for the same
# capture, not unique to it, and hashing all of a 1920 x 1200 frame took 40-70 ms of each
# service answer.
DIGEST_STRIDE = 16


def derive_seed(seed: int, *names: str | int) -> np.random.SeedSequence:
    """A SeedSequence from the base seed and a path of names (strings hashed with CRC-32)."""
    words = [int(seed)] + [zlib.crc32(n.encode()) if isinstance(n, str) else int(n) for n in names]
    return np.random.SeedSequence(words)


def derive_int(seed: int, *names: str | int) -> int:
    """A 31-bit integer seed (for libraries that take an int) derived like derive_seed."""
    return int(derive_seed(seed, *names).generate_state(1)[0] & 0x7FFFFFFF)


def capture_digest(xyz_m: np.ndarray, rgb: np.ndarray | None) -> str:
    """16 hex digits naming a capture by its content (xyz_m (n, 3) as read, NaN = no return;
    rgb (n, 3) uint8 or None): every step of the scene path draws its seeds from it, so that the
    service and the DVC stages give the same capture the same answer, whatever its file is called."""
    h = hashlib.sha256(np.ascontiguousarray(xyz_m[::DIGEST_STRIDE]).data)
    if rgb is not None:
        h.update(np.ascontiguousarray(rgb[::DIGEST_STRIDE]).data)
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class SceneSeeds:
    """The seed of each step of the scene path (binpick/scene/). `of_capture` derives them from
    the project seed and the capture's content, as the service and the DVC stages do; `of(seed,
    name)` from a name (benchmarks, tests)."""

    clean: int
    segment: np.random.SeedSequence
    register: np.random.SeedSequence

    @classmethod
    def of(cls, seed: int, name: str) -> SceneSeeds:
        return cls(
            derive_int(seed, "import", name), derive_seed(seed, "segment", name), derive_seed(seed, "register", name)
        )

    @classmethod
    def of_capture(cls, seed: int, xyz_m: np.ndarray, rgb: np.ndarray | None) -> SceneSeeds:
        """The seeds of a capture by its content (capture_digest): the same in the service and
        the DVC stages, so that a kept request run again by the pipeline gives the robot's answer."""
        return cls.of_capture_digest(seed, capture_digest(xyz_m, rgb))

    @classmethod
    def of_capture_digest(cls, seed: int, digest: str) -> SceneSeeds:
        return cls.of(seed, f"capture-{digest}")


def scene_seeds(seed: int, digest: str, path: str | Path) -> SceneSeeds:
    """The seeds of the steps after import for a cleaned cloud: by the capture digest the import
    stage stored in it; by the cloud's path for clouds written before it had one (digest '')."""
    return SceneSeeds.of_capture_digest(seed, digest) if digest else SceneSeeds.of(seed, str(path))
