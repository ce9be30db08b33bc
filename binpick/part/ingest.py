"""Ingest: a part's CAD mesh, in its declared unit, becomes a part model in metres.

The unit is checked, not trusted: a part too small or too large for the camera and bin it will be
imaged with is refused, naming the unit that would fit; `auto` picks the first unit that fits.
A mesh of separate bodies (an assembly) is refused. Large meshes are decimated to
ingest.max_faces after their diameter is taken from the full mesh.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.mesh import METRES_PER_UNIT, guess_unit, read_mesh
from binpick.io.part_model import PartModel
from binpick.params import Params
from binpick.part.model import diameter, make_part_model, simplify_mesh
from binpick.part.scale import Imaging, bodies, describe_size, fitting_units, scale_problem, size_warning
from binpick.seeding import derive_seed

log = logging.getLogger(__name__)


def imaging_for(params: Params) -> Imaging:
    """The part's bin, camera and grids, from its resolved params."""
    cam = params.camera
    return Imaging(
        bin_x_m=params.generate.bin.inner_x_m,
        bin_y_m=params.generate.bin.inner_y_m,
        view_m=cam.distance_m * min(cam.width_px / cam.fx_px, cam.height_px / cam.fy_px),
        pixel_m=cam.distance_m / cam.fx_px * cam.downscale,
        voxel_m=params.import_capture.voxel_size_m,
        min_points=params.segment.min_points,
    )


def ingest_part(params: Params, part: str, mesh_path: Path) -> tuple[PartModel, dict[str, float | str]]:
    """Read, check and simplify a part's CAD mesh; the part model (metres) and its metrics.

    params: resolved for `part`. Raises InputError (one line naming the file) for a mesh that
    cannot be a part with these settings.
    """
    t0 = time.perf_counter()
    spec = params.parts[part]
    mesh = read_mesh(mesh_path)  # file units
    n_faces_in = len(mesh.faces)
    d_file, area_file = diameter(mesh.vertices), float(mesh.area)
    imaging = imaging_for(params)
    fits = fitting_units(d_file, area_file, imaging)
    unit: str = spec.unit
    if unit == "auto":
        unit = fits[0] if fits else guess_unit(float(np.max(mesh.extents)))
        log.warning(
            "%s: unit not declared; guessed %r (the part is then %s across)",
            mesh_path,
            unit,
            describe_size(d_file, unit),
        )
    scale = METRES_PER_UNIT[unit]
    problem = scale_problem(d_file * scale, area_file * scale**2, imaging)
    if problem:
        likely = [u for u in fits if u != unit]
        hint = (
            f"; in {likely[0]!r} it would be {describe_size(d_file, likely[0])}: declare `unit: {likely[0]}` "
            f"(parts.{part}.unit)"
            if likely
            else f"; declare the right unit (parts.{part}.unit), or give the part its own camera and bin settings"
        )
        raise InputError(
            mesh_path, f"read as {unit!r} the part is {describe_size(d_file, unit)} across, {problem}{hint}"
        )
    extent = float(np.max(mesh.extents)) * scale
    if not params.ingest.min_extent_m <= extent <= params.ingest.max_extent_m:
        raise InputError(
            mesh_path,
            f"part is {extent:.4g} m long in unit {unit!r}, outside {params.ingest.min_extent_m}-"
            f"{params.ingest.max_extent_m} m: declare the right unit in params.yaml (parts.{part}.unit)",
        )
    mesh.apply_scale(scale)
    d_m = d_file * scale
    mesh = simplify_mesh(mesh, params.ingest.max_faces)
    found = bodies(mesh, d_m)
    if found.n_groups > 1:
        raise InputError(
            mesh_path,
            f"holds {found.n_groups} separate bodies up to {found.largest_gap_m * 1000:.0f} mm apart: "
            "an assembly, not one part (export one part per file)",
        )
    if found.n_pieces > 1:
        log.warning("%s: %d touching or nested shells taken as one part", mesh_path, found.n_pieces)
    if warning := size_warning(d_m, imaging):
        log.warning("%s: %s", mesh_path, warning)
    mesh.fix_normals()
    if not mesh.is_watertight:
        log.warning("%s: mesh is not watertight; normals may point inward in places", mesh_path)
    rng = np.random.default_rng(derive_seed(params.seed, "ingest", part))
    model = make_part_model(part, mesh, spec.symmetry, params.ingest.n_surface_points, rng, unit, diameter_m=d_m)
    metrics: dict[str, float | str] = {
        "diameter_mm": 1000.0 * model.diameter_m,
        "n_faces": float(len(model.mesh_faces)),
        "n_faces_in": float(n_faces_in),
        "n_bodies": float(found.n_pieces),
        "unit": unit,
        "watertight": float(model.watertight),
        "extent_x_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 0])),
        "extent_y_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 1])),
        "extent_z_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 2])),
        "ingest_s": time.perf_counter() - t0,
    }
    log.info(
        "%s: %s (diameter %.1f mm, unit %s, %d of %d faces)",
        part,
        mesh_path,
        metrics["diameter_mm"],
        unit,
        len(model.mesh_faces),
        n_faces_in,
    )
    return model, metrics
