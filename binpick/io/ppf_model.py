"""Trained PPF models (`ppf.npz`). Spec: data/README.md#ppf-model."""

from __future__ import annotations

from pathlib import Path

from binpick.io.npz import load_fields, save_fields
from binpick.registration.ppf import PPFModel


def save_ppf_model(path: str | Path, model: PPFModel) -> None:
    save_fields(path, model, compressed=False)  # loaded on every registration: no inflating


def load_ppf_model(path: str | Path) -> PPFModel:
    values = load_fields(path, PPFModel, "PPF model", "PPF model not found (run the ppf stage first)")
    for name in ("diameter_m", "distance_step_m"):
        values[name] = float(values[name])
    values["angle_bins"] = int(values["angle_bins"])
    return PPFModel(**values)
