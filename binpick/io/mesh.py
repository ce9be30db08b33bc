"""CAD meshes (STL, PLY, OBJ, OFF) in, triangle meshes in metres out.

Mesh files carry no unit; the caller declares it (`mm`, `m`, `in`) or asks for a logged guess
(`auto`). This is the one place where a CAD unit becomes metres.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from binpick.errors import InputError

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".stl", ".ply", ".obj", ".off")
METRES_PER_UNIT = {"m": 1.0, "mm": 1e-3, "in": 0.0254}


def guess_unit(max_extent: float) -> str:
    """Guess the unit of a mesh from its largest extent in file units.

    Bin-picking parts are between a few millimetres and about a metre, so an extent of at most
    2 reads as metres and anything larger as millimetres. Inches cannot be told from millimetres
    by size alone: declare `in` for them.
    """
    return "m" if max_extent <= 2.0 else "mm"


def read_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a triangle mesh in the units of its file: vertices merged, degenerate faces dropped.

    Raises InputError naming the file for a missing, unreadable or empty mesh.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(path, f"unsupported mesh extension {path.suffix!r} (use one of {', '.join(MESH_SUFFIXES)})")
    if path.stat().st_size == 0:
        raise InputError(path, "file is empty")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputError(path, "has non-finite vertex coordinates")
    n_before = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise InputError(path, "all triangles are degenerate")
    if len(mesh.faces) < n_before:
        log.warning("%s: dropped %d degenerate faces of %d", path, n_before - len(mesh.faces), n_before)
    return mesh


def load_mesh(path: str | Path, unit: str) -> tuple[trimesh.Trimesh, str]:
    """Load a triangle mesh and scale it to metres.

    Returns the mesh (vertices in metres, model frame of the file, faces with consistent
    outward winding where the mesh is closed) and the unit that was applied (`auto`: guessed
    from the size alone; the ingest stage guesses better, from the camera and bin too).
    Raises InputError naming the file for a missing, unreadable or empty mesh.
    """
    mesh = read_mesh(path)
    extent = float(np.max(mesh.extents))
    if unit == "auto":
        unit = guess_unit(extent)
        log.warning("%s: unit not declared; guessed %r from its largest extent %.4g", path, unit, extent)
    if unit not in METRES_PER_UNIT:
        raise InputError(path, f"unknown unit {unit!r} (use mm, m, in or auto)")
    mesh.apply_scale(METRES_PER_UNIT[unit])
    mesh.fix_normals()
    if not mesh.is_watertight:
        log.warning("%s: mesh is not watertight; normals may point inward in places", path)
    return mesh, unit


def save_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a mesh (any unit the caller chose) in the format of the extension of `path`."""
    from binpick.io.atomic import atomic_path

    mesh = trimesh.Trimesh(vertices=np.asarray(vertices), faces=np.asarray(faces), process=False)
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=Path(path).suffix.lower().lstrip("."))
