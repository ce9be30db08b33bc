"""Part model files (`part.npz`): the ingested CAD model in metres, ready for every stage.

Spec: data/README.md#part-model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_path
from binpick.params import SymmetryParams


@dataclass(frozen=True)
class PartModel:
    """A part in its CAD model frame, metres.

    mesh_vertices_m : (v, 3) float64, model frame
    mesh_faces      : (f, 3) int64, outward winding where the mesh is closed
    points_m        : (n, 3) float32, dense surface sample, model frame
    normals         : (n, 3) float32, unit outward surface normals at `points_m`
    diameter_m      : largest distance between two points of the part
    centre_m        : (3,) centre of the bounding box, model frame
    """

    name: str
    mesh_vertices_m: np.ndarray
    mesh_faces: np.ndarray
    points_m: np.ndarray
    normals: np.ndarray
    diameter_m: float
    centre_m: np.ndarray
    symmetry: SymmetryParams
    source_unit: str
    watertight: bool


def save_part_model(path: str | Path, model: PartModel) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp,
            name=np.array(model.name),
            mesh_vertices_m=model.mesh_vertices_m.astype(np.float64),
            mesh_faces=model.mesh_faces.astype(np.int64),
            points_m=model.points_m.astype(np.float32),
            normals=model.normals.astype(np.float32),
            diameter_m=np.float64(model.diameter_m),
            centre_m=np.asarray(model.centre_m, dtype=np.float64),
            symmetry_json=np.array(model.symmetry.model_dump_json()),
            source_unit=np.array(model.source_unit),
            watertight=np.bool_(model.watertight),
        )


def load_part_model(path: str | Path) -> PartModel:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "part model not found (run the ingest stage first)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return PartModel(
                name=str(z["name"]),
                mesh_vertices_m=z["mesh_vertices_m"],
                mesh_faces=z["mesh_faces"],
                points_m=z["points_m"],
                normals=z["normals"],
                diameter_m=float(z["diameter_m"]),
                centre_m=z["centre_m"],
                symmetry=SymmetryParams.model_validate(json.loads(str(z["symmetry_json"]))),
                source_unit=str(z["source_unit"]),
                watertight=bool(z["watertight"]),
            )
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(path, f"not a binpick part model ({exc})") from None
