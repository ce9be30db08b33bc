"""FPCC checkpoints (`.pt`): config, weights, optimiser, epoch, metrics, and what inference needs
(`InferenceSettings`, stored as the checkpoint's `extra` mapping and rebuilt from it here, the one
place that reads its keys).

A checkpoint rebuilds its network on its own: `load_network(path)` needs nothing else.
Spec: data/README.md#checkpoint.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from binpick.errors import InputError
from binpick.io.atomic import atomic_path
from binpick.network.model import FPCC, FPCCConfig
from binpick.params import TrainParams

# 2: a SHA-256 of the weights and settings (`sha256`), checked on every load.
CHECKPOINT_VERSION = 2


@dataclass(frozen=True)
class CalibratedClustering:
    """Clustering settings chosen on the validation scenes after training (network/calibrate.py):
    centre score threshold, embedding distance threshold, smallest instance kept (points), and the
    foreground head's logit above which a point is a part's (0 in checkpoints calibrated before it
    was chosen)."""

    centre_threshold: float
    embedding_threshold: float
    min_instance_points: int
    foreground_logit: float = 0.0

    def to_dict(self) -> dict[str, float]:
        return {
            "centre_threshold": self.centre_threshold,
            "embedding_threshold": self.embedding_threshold,
            "min_instance_points": self.min_instance_points,
            "foreground_logit": self.foreground_logit,
        }


@dataclass(frozen=True)
class InferenceSettings:
    """What a trained network needs besides its weights: the part it segments and that part's
    diameter (metres), the input features and d_max (metres) it was trained with, its training
    settings (eps2 of the loss bounds the calibration grid), and the calibrated clustering (None
    until calibration ran)."""

    part: str
    part_diameter_m: float
    features: str
    d_max_m: float
    train: TrainParams
    clustering: CalibratedClustering | None = None
    # The pose verification threshold (register.max_seen_through) chosen on the validation
    # scenes after training (binpick/scene/verification_threshold.py); None until chosen.
    max_seen_through: float | None = None
    # ... and register.min_visible_support, chosen with it (None: not chosen, as in checkpoints
    # calibrated before it existed).
    min_visible_support: float | None = None

    def to_extra(self) -> dict[str, Any]:
        """The stored form. Key order is part of the file's bytes: keep it."""
        extra: dict[str, Any] = {
            "part": self.part,
            "part_diameter_m": self.part_diameter_m,
            "features": self.features,
            "train_params": self.train.model_dump(),
            "d_max_m": self.d_max_m,
        }
        if self.clustering is not None:
            extra["clustering"] = self.clustering.to_dict()
        if self.max_seen_through is not None:
            extra["verification"] = _verification(self.max_seen_through, self.min_visible_support)
        return extra

    @classmethod
    def from_extra(cls, extra: dict[str, Any], path: str | Path = "checkpoint") -> InferenceSettings:
        try:
            clustering = extra.get("clustering")
            return cls(
                part=str(extra["part"]),
                part_diameter_m=float(extra["part_diameter_m"]),
                features=str(extra["features"]),
                d_max_m=float(extra["d_max_m"]),
                train=TrainParams.model_validate(extra["train_params"]),
                clustering=None
                if clustering is None
                else CalibratedClustering(
                    float(clustering["centre_threshold"]),
                    float(clustering["embedding_threshold"]),
                    int(clustering["min_instance_points"]),
                    float(clustering.get("foreground_logit", 0.0)),
                ),
                max_seen_through=float(extra["verification"]["max_seen_through"]) if "verification" in extra else None,
                min_visible_support=(
                    float(extra["verification"]["min_visible_support"])
                    if "min_visible_support" in extra.get("verification", {})
                    else None
                ),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"holds no complete inference settings ({type(exc).__name__}: {exc})") from None


def save_checkpoint(
    path: str | Path,
    model: FPCC,
    optimiser: torch.optim.Optimizer | None,
    epoch: int,
    metrics: dict[str, float],
    extra: dict[str, Any],
) -> None:
    """extra: InferenceSettings.to_extra() and what training adds (seed, data fingerprint)."""
    state = {
        "version": CHECKPOINT_VERSION,
        "config": model.config.to_dict(),
        "model": model.state_dict(),
        "optimiser": optimiser.state_dict() if optimiser is not None else None,
        "epoch": epoch,
        "metrics": metrics,
        "extra": extra,
    }
    write_state(path, state)


def content_sha256(state: dict[str, Any]) -> str:
    """SHA-256 of what a checkpoint means: every weight tensor (name, dtype, shape, bytes) in
    name order, the optimiser's tensors, and the config, epoch, metrics and extra as JSON. A
    flipped byte that torch still reads changes it."""
    h = hashlib.sha256()

    def tensors(prefix: str, value: Any) -> None:
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous()
            h.update(f"{prefix}|{t.dtype}|{tuple(t.shape)}|".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        elif isinstance(value, dict):
            for key in sorted(value, key=str):
                tensors(f"{prefix}/{key}", value[key])
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                tensors(f"{prefix}/{i}", item)
        else:
            h.update(f"{prefix}={value!r}|".encode())

    tensors("model", state["model"])
    tensors("optimiser", state.get("optimiser"))
    h.update(
        json.dumps(
            {k: state.get(k) for k in ("version", "config", "epoch", "metrics", "extra")}, sort_keys=True, default=str
        ).encode()
    )
    return h.hexdigest()


def write_with_clustering(source: str | Path, out: str | Path, clustering: CalibratedClustering) -> None:
    """Write the checkpoint at source to out with its calibrated clustering replaced."""
    state = read_checkpoint(source)
    state["extra"] = {**state["extra"], "clustering": clustering.to_dict()}
    state.pop("sha256", None)
    write_state(out, state)


def _verification(max_seen_through: float, min_visible_support: float | None) -> dict[str, float]:
    out = {"max_seen_through": float(max_seen_through)}
    if min_visible_support is not None:
        out["min_visible_support"] = float(min_visible_support)
    return out


def write_finetuned(
    trained: str | Path,
    out: str | Path,
    base_state: dict[str, Any],
    base_sha256: str,
    learnt: list[str],
    judged: list[str],
) -> None:
    """Write the fine-tuned checkpoint at trained to out with the calibrated clustering and
    verification thresholds of the network it was fine-tuned from (base_state: fine-tuning does
    not move them far; the next full training recalibrates), the SHA-256 of the trained network
    it descends from, and the captures it learnt from and was judged by."""
    state = read_checkpoint(trained)
    carried = {k: base_state["extra"][k] for k in ("clustering", "verification") if k in base_state["extra"]}
    state["extra"] = {
        **state["extra"],
        **carried,
        "finetuned_from": base_sha256,
        "real_scenes": learnt,
        "real_heldout": judged,
    }
    state.pop("sha256", None)
    write_state(out, state)


def read_settings(path: str | Path) -> InferenceSettings:
    """A checkpoint's inference settings, without building its network."""
    return InferenceSettings.from_extra(read_checkpoint(path)["extra"], path)


def write_state(path: str | Path, state: dict[str, Any]) -> None:
    """Write a checkpoint's entries, with a fresh checksum of them."""
    # Through a buffer: torch names the archive inside the file after the file, and the atomic
    # write's temporary name would make equal checkpoints differ byte for byte.
    state = {**state, "version": CHECKPOINT_VERSION}
    state["sha256"] = content_sha256(state)
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
    if not isinstance(state, dict) or "version" not in state:
        raise InputError(path, "not a binpick FPCC checkpoint")
    if state["version"] != CHECKPOINT_VERSION:
        raise InputError(
            path,
            f"a checkpoint of format version {state['version']}, this binpick reads {CHECKPOINT_VERSION}: train the "
            "part again",
        )
    try:
        intact = state.get("sha256") == content_sha256(state)
    except Exception:  # noqa: BLE001 - a damaged structure is a damaged file
        intact = False
    if not intact:
        raise InputError(
            path,
            "damaged: its weights do not match the checksum stored with them (copy it again, or train the part again)",
        )
    return state


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[FPCC, dict[str, Any]]:
    """The network in eval mode on `device`, and the checkpoint's other entries."""
    state = read_checkpoint(path, device)
    model = FPCC(FPCCConfig(**state["config"]))
    model.load_state_dict(state["model"])
    model.to(device).eval()
    return model, state


def load_network(path: str | Path, device: str | torch.device = "cpu") -> tuple[FPCC, InferenceSettings]:
    """The network in eval mode on `device`, and its inference settings."""
    model, state = load_checkpoint(path, device)
    return model, InferenceSettings.from_extra(state["extra"], path)
