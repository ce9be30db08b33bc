"""Review records (`data/real/<part>/reviewed.json`): a person's verdict on each labelled capture,
tied to the SHA-256 of the file reviewed. Spec: data/README.md#folders."""

from __future__ import annotations

import json
from pathlib import Path

from binpick.errors import InputError
from binpick.io.atomic import write_text


def load_review_record(path: Path) -> dict[str, dict]:
    """capture -> {"sha256": of the labelled file reviewed, "approved": bool}; {} when none."""
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text())
        return {str(k): {"sha256": str(v["sha256"]), "approved": bool(v["approved"])} for k, v in doc.items()}
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(path, f"not a review record ({type(exc).__name__}: {exc})") from None


def save_review_record(path: Path, verdicts: dict[str, dict]) -> None:
    """Write atomically, captures sorted by name."""
    write_text(path, json.dumps(dict(sorted(verdicts.items())), indent=1) + "\n")
