"""Atomic writes: a reader never sees a half-written file, a failed writer leaves nothing."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import overload

from binpick.lifetime import pid_alive


def sweep_stale(parent: Path, prefix: str) -> None:
    """Remove temporaries `<prefix><pid>.*.tmp*` in `parent` left by writers that were killed
    (their process is gone); a live writer's are left alone."""
    if not parent.is_dir():
        return
    for stale in parent.glob(f"{prefix}*.tmp*"):
        pid = stale.name[len(prefix) :].split(".", 1)[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
            else:
                stale.unlink(missing_ok=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to `path`; move it onto `path` only if the block succeeds.

    The temporary file keeps the suffix of `path` so that writers which choose a format from the
    extension (numpy, PIL, open3d) behave as for the real name.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The writer's pid in the name: a killed writer's temporary is swept by the next one.
    prefix = f".{path.stem}."
    sweep_stale(path.parent, prefix)
    fd, tmp_name = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file normal permissions
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary folder next to `path`; it replaces `path` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{path.name}."
    sweep_stale(path.parent, prefix)
    tmp = Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


@overload
def atomic_paths(
    out: str | Path, other: str | Path | None, /
) -> contextlib.AbstractContextManager[tuple[Path, Path | None]]: ...
@overload
def atomic_paths(
    out: str | Path, other: str | Path | None, third: str | Path | None, /
) -> contextlib.AbstractContextManager[tuple[Path, Path | None, Path | None]]: ...
def atomic_paths(*paths: str | Path | None) -> contextlib.AbstractContextManager[tuple[Path | None, ...]]:
    """Temporary paths for several outputs that are committed together: each moves onto its real
    path only after the whole block succeeded; a failure anywhere leaves every real path as it
    was. None stays None (an output not asked for; the first output is always asked for).
    Suffixes are kept, as in atomic_path."""
    return _atomic_paths(*paths)


@contextlib.contextmanager
def _atomic_paths(*paths: str | Path | None) -> Iterator[tuple[Path | None, ...]]:
    temps: list[Path | None] = []
    try:
        for p in paths:
            if p is None:
                temps.append(None)
                continue
            p = Path(p)
            p.parent.mkdir(parents=True, exist_ok=True)
            prefix = f".{p.stem}."
            sweep_stale(p.parent, prefix)
            fd, name = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}.", suffix=f".tmp{p.suffix}", dir=p.parent)
            os.close(fd)
            temps.append(Path(name))
        yield tuple(temps)
        for p, tmp in zip(paths, temps, strict=True):
            if p is not None and tmp is not None:
                if not tmp.exists() or tmp.stat().st_size == 0:
                    raise FileNotFoundError(f"{p}: the stage wrote nothing there")
                os.chmod(tmp, 0o666 & ~_umask())
        for p, tmp in zip(paths, temps, strict=True):
            if p is not None and tmp is not None:
                os.replace(tmp, p)
    finally:
        for tmp in temps:
            if tmp is not None and tmp.exists():
                tmp.unlink()
