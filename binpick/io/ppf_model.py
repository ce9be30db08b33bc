"""Trained PPF models (`ppf.npz`). Spec: data/README.md#ppf-model."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_path
from binpick.registration.ppf import PPFModel


def save_ppf_model(path: str | Path, model: PPFModel) -> None:
    with atomic_path(path) as tmp:
        np.savez(tmp, **{f.name: np.asarray(getattr(model, f.name)) for f in fields(PPFModel)})


def load_ppf_model(path: str | Path) -> PPFModel:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "PPF model not found (run the ppf stage first)")
    try:
        with np.load(path, allow_pickle=False) as z:
            values = {f.name: z[f.name] for f in fields(PPFModel)}
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(path, f"not a binpick PPF model ({exc})") from None
    for name in ("diameter_m", "distance_step_m"):
        values[name] = float(values[name])
    values["angle_bins"] = int(values["angle_bins"])
    return PPFModel(**values)
