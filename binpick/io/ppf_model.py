"""Trained PPF models (`ppf.npz`) and their type. Spec: data/README.md#ppf-model."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from pykdtree.kdtree import KDTree

from binpick.io.npz import load_fields, save_fields


@dataclass(frozen=True)
class PPFModel:
    """A trained PPF model.

    points_m (M, 3), normals (M, 3): subsampled model surface, model frame.
    keys (P,) int64 sorted; ref_index (P,) int32 model reference point of each pair; alpha (P,)
    float32 angle alpha_m of each pair, radians in (-pi, pi]; key_starts (K + 1,) int64: the pairs
    of key k are keys[key_starts[k]:key_starts[k + 1]] (an O(1) lookup).
    dense_points_m, dense_normals: the full surface sample, for scoring and ICP.
    symmetries (m, 4, 4): transforms of the model frame onto itself, identity first.
    near_symmetries (k, 4, 4): turns of the model frame that map nearly all of the surface onto
    itself but are not symmetries (registration/model.py); k = 0 for most parts.
    sample_step_m: the voting grid of model and scene (metres); NaN in files written before it
    was stored, whose grid is the register params' sample_step_rel of the diameter.
    """

    points_m: np.ndarray
    normals: np.ndarray
    keys: np.ndarray
    ref_index: np.ndarray
    alpha: np.ndarray
    key_starts: np.ndarray
    dense_points_m: np.ndarray
    dense_normals: np.ndarray
    symmetries: np.ndarray
    near_symmetries: np.ndarray
    diameter_m: float
    distance_step_m: float
    angle_bins: int
    sample_step_m: float = float("nan")

    @cached_property
    def dense_tree(self) -> KDTree:
        """A k-d tree of dense_points_m (model frame), built on first use and kept with the model
        (pykdtree: nearest-neighbour queries only, twice scipy's speed)."""
        return KDTree(np.ascontiguousarray(self.dense_points_m, dtype=np.float64))

    @cached_property
    def revolution_axis(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(unit axis (3,), a point on it (3,)), model frame, when the symmetries are a sampled
        revolution (ICP leaves the turn about it free); None otherwise."""
        from binpick.geometry.symmetry import revolution_axis

        return revolution_axis(self.symmetries)

    @cached_property
    def dense_normal_dot_point(self) -> np.ndarray:
        """(D,) n . p of each dense point and its normal (model frame, metres), kept with the model:
        at pose (R, t) a point faces the camera at the origin when n . p + n . (R^T t) < 0."""
        n, p = self.dense_normals.astype(np.float64), self.dense_points_m.astype(np.float64)
        return n[:, 0] * p[:, 0] + n[:, 1] * p[:, 1] + n[:, 2] * p[:, 2]


def save_ppf_model(path: str | Path, model: PPFModel) -> None:
    save_fields(path, model, compressed=False)  # loaded on every registration: no inflating


def load_ppf_model(path: str | Path) -> PPFModel:
    # Models written before near symmetries were found have none, and those written before the
    # voting grid was stored used the params' (the ppf stage rebuilds both).
    values: dict[str, Any] = dict(
        load_fields(
            path,
            PPFModel,
            "PPF model",
            "PPF model not found (run the ppf stage first)",
            {"near_symmetries": np.zeros((0, 4, 4)), "sample_step_m": np.array(np.nan)},
        )
    )
    for name in ("diameter_m", "distance_step_m", "sample_step_m"):
        values[name] = float(values[name])
    values["angle_bins"] = int(values["angle_bins"])
    return PPFModel(**values)
