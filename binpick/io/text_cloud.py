"""Point clouds as text: CSV or whitespace-separated XYZ, one point per line, columns named by
the caller (Zivid's CSV export: x, y, z, r, g, b, contrast).

Column names: x, y, z (required), r, g, b (0-255), nx, ny, nz, label, score; `_` or any other
name is read and ignored. Lines with the wrong number of values (a truncated last row) are
skipped and counted.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from binpick.errors import InputError

log = logging.getLogger(__name__)


def load_text_columns(path: str | Path, columns: list[str]) -> dict[str, np.ndarray]:
    """The named columns of a text cloud as float64 arrays, plus 'skipped_rows' (count, shape ())."""
    path = Path(path)
    if not {"x", "y", "z"} <= set(columns):
        raise InputError(path, f"columns {columns} must name x, y and z")
    text = path.read_text(errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    if not lines:
        raise InputError(path, "holds no points")
    sep = "," if "," in lines[0] else None
    n_cols = len(columns)
    rows, skipped = [], 0
    for ln in lines:
        parts = ln.split(sep)
        if len(parts) != n_cols:
            skipped += 1
            continue
        rows.append(parts)
    if not rows:
        raise InputError(path, f"no line has the {n_cols} columns {columns}")
    try:
        table = np.asarray(rows, dtype=np.float64)
    except ValueError:
        # A header line of names, or stray text: keep the numeric rows.
        good = []
        for r in rows:
            try:
                good.append([float(v) for v in r])
            except ValueError:
                skipped += 1
        if not good:
            raise InputError(path, "holds no numeric rows") from None
        table = np.asarray(good)
    if skipped:
        log.warning("%s: skipped %d malformed or incomplete lines", path, skipped)
    out = {name: table[:, k] for k, name in enumerate(columns) if name != "_"}
    out["skipped_rows"] = np.asarray(skipped)
    return out
