"""Dataclasses of arrays stored as `.npz` files, one array per field: the shared mechanics of
the project's npz formats (scenes, cleaned clouds, PPF models)."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_path

T = TypeVar("T")


def save_fields(path: str | Path, obj: Any, compressed: bool = True) -> None:
    """Write every field of a dataclass as an array, atomically. Same content, same bytes."""
    arrays = {f.name: np.asarray(getattr(obj, f.name)) for f in fields(obj)}
    with atomic_path(path) as tmp:
        if compressed:
            np.savez_compressed(tmp, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as bool
        else:
            np.savez(tmp, **arrays)  # type: ignore[arg-type]


def load_fields(
    path: str | Path, cls: type[T], what: str, missing: str, defaults: dict[str, np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """The arrays of the fields of `cls` from `path` (`defaults` for fields that files written
    before them lack); InputError naming the file when it is missing (`missing` says how to make
    it) or is not a `what`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, missing)
    try:
        with np.load(path, allow_pickle=False) as z:
            absent = {k: v for k, v in (defaults or {}).items() if k not in z.files}
            return {f.name: absent[f.name] if f.name in absent else z[f.name] for f in fields(cls)}  # type: ignore[arg-type]  # cls is a dataclass
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(path, f"not a binpick {what} ({exc})") from None
