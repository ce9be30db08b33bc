"""A part's pose verification thresholds (`data/fpcc/<part>/verification.json`), chosen by the
verify stage on the validation scenes with the part's network. Spec: data/README.md#folders.

{"max_seen_through": float, "min_visible_support": float, "checkpoint_sha256": str,
"support_incidence_deg": float}: the most of a pose's camera-facing surface that may lie where the
camera saw through it, the least share of it in view that must have a measurement on it
(registration/visibility.py), the network the verify stage chose them with, and the incidence up
to which that share counted surface (registration/constants.py, SUPPORT_MAX_INCIDENCE_DEG; absent
in files written before the limit, whose support cut counted all facing surface).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from binpick.errors import InputError
from binpick.io.atomic import write_text


@dataclass(frozen=True)
class Verification:
    max_seen_through: float
    min_visible_support: float | None  # None: chosen before the support check existed (older checkpoints)
    checkpoint_sha256: str = ""  # "" when read from a checkpoint's own settings
    # The incidence limit the support cut was chosen with; None: before the limit (all facing
    # surface counted), so the cut means something else today and is not used (register.py).
    support_incidence_deg: float | None = None


def save_verification(path: str | Path, chosen: Verification) -> None:
    write_text(path, json.dumps(asdict(chosen), indent=1) + "\n")


def load_verification(path: str | Path) -> Verification:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "verification thresholds not found (run the verify stage first)")
    try:
        doc = json.loads(path.read_text())
        incidence = doc.get("support_incidence_deg")
        chosen = Verification(
            float(doc["max_seen_through"]),
            float(doc["min_visible_support"]),
            str(doc["checkpoint_sha256"]),
            None if incidence is None else float(incidence),
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"not a verification file ({type(exc).__name__}: {exc})") from None
    if not (0.0 <= chosen.max_seen_through <= 1.0 and 0.0 <= (chosen.min_visible_support or 0.0) <= 1.0):
        raise InputError(path, f"thresholds outside [0, 1]: {chosen.max_seen_through}, {chosen.min_visible_support}")
    return chosen
