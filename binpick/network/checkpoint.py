"""FPCC checkpoints (`.pt`): config, weights, optimiser, epoch, metrics, and what inference needs.

A checkpoint rebuilds its network on its own: `load_checkpoint(path)` needs nothing else.
Spec: data/README.md#checkpoint.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from binpick.errors import InputError
from binpick.io.atomic import atomic_path
from binpick.network.model import FPCC, FPCCConfig

CHECKPOINT_VERSION = 1


def save_checkpoint(
    path: str | Path,
    model: FPCC,
    optimiser: torch.optim.Optimizer | None,
    epoch: int,
    metrics: dict[str, float],
    extra: dict[str, Any],
) -> None:
    """extra holds inference settings tied to training: d_max_m, features, part_diameter_m, ..."""
    state = {
        "version": CHECKPOINT_VERSION,
        "config": model.config.to_dict(),
        "model": model.state_dict(),
        "optimiser": optimiser.state_dict() if optimiser is not None else None,
        "epoch": epoch,
        "metrics": metrics,
        "extra": extra,
    }
    _write(path, state)


def update_extra(source: str | Path, out: str | Path, **entries: Any) -> None:
    """Write the checkpoint at source to out with entries added to its extra (e.g. settings
    chosen after training)."""
    state = read_checkpoint(source)
    state["extra"] = {**state["extra"], **entries}
    _write(out, state)


def _write(path: str | Path, state: dict[str, Any]) -> None:
    # Through a buffer: torch names the archive inside the file after the file, and the atomic
    # write's temporary name would make equal checkpoints differ byte for byte.
    buffer = io.BytesIO()
    torch.save(state, buffer)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buffer.getvalue())


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "checkpoint not found (train the part first)")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises many types for damaged files
        raise InputError(path, f"not a readable checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        raise InputError(path, "not a binpick FPCC checkpoint of this version")
    return state


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[FPCC, dict[str, Any]]:
    """The network in eval mode on `device`, and the checkpoint's other entries."""
    state = read_checkpoint(path, device)
    model = FPCC(FPCCConfig(**state["config"]))
    model.load_state_dict(state["model"])
    model.to(device).eval()
    return model, state
