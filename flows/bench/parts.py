"""The parts benchmarks run on: the built-in part and, when present, the real parts in
../shared/data/parts with their units and symmetries."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.io.mesh import load_mesh
from binpick.io.part_model import PartModel
from binpick.params import SymmetryParams
from binpick.part.model import DEFAULT_PART_NAME, T_JOINT_SYMMETRY, build_t_joint_mesh, make_part_model

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchPart:
    file: str
    unit: str
    symmetry: SymmetryParams


# Units and symmetries from ../shared/data/MANIFEST.md and the meshes' extents.
SHARED_PARTS = {
    "ipa_gear_shaft": BenchPart("ipa_gear_shaft.stl", "m", SymmetryParams(kind="revolution", axis=(0, 0, 1))),
    # Two-fold about the long axis: turning the eye bolt half a turn maps the ring onto itself (the
    # thread differs by about 1% of the size, below what a 3D camera resolves).
    "ipa_ring_screw": BenchPart("ipa_ring_screw.stl", "m", SymmetryParams(kind="n_fold", axis=(0, 0, 1), order=2)),
    # A T like the built-in part: two-fold about its branch axis (y), which passes through the
    # centre of its box (the file's origin is a corner).
    "zju_three_way_pipe": BenchPart(
        "zju_three_way_pipe.stl",
        "mm",
        SymmetryParams(kind="n_fold", axis=(0, 1, 0), order=2, origin_m=(0.017, 0.0, 0.031)),
    ),
    # Despite its name the nut has eight sides (a 45 degree turn maps it onto itself within
    # 0.02 mm on average, a 60 degree one leaves 0.4 mm): eight-fold about its axis (y) through its
    # centre, which lies far from the file's origin, and its two faces alike (a flip about x).
    "hex_nut": BenchPart(
        "hex_nut.ply",
        "mm",
        SymmetryParams(
            kind="n_fold", axis=(0, 1, 0), order=8, origin_m=(0.0813611, -0.0819074, -0.0813611), flip_axis=(1, 0, 0)
        ),
    ),
    "featuretype_inch": BenchPart("featuretype_inch.stl", "in", SymmetryParams()),
}


def shared_parts_folder() -> Path | None:
    from binpick.env import project_root

    folder = project_root().parent / "shared" / "data" / "parts"
    return folder if folder.is_dir() else None


def bench_parts(names: list[str] | None, n_points: int = 20000, seed: int = 0) -> list[PartModel]:
    """Part models of the requested parts (default: the built-in part and every shared part found)."""
    wanted = names or [DEFAULT_PART_NAME, *SHARED_PARTS]
    folder = shared_parts_folder()
    models = []
    for name in wanted:
        rng = np.random.default_rng(seed)
        if name == DEFAULT_PART_NAME:
            mesh = build_t_joint_mesh()
            mesh.apply_scale(1e-3)
            models.append(make_part_model(name, mesh, T_JOINT_SYMMETRY, n_points, rng, "mm"))
            continue
        spec = SHARED_PARTS.get(name)
        if spec is None:
            raise ValueError(f"unknown benchmark part {name!r} (have: {DEFAULT_PART_NAME}, {', '.join(SHARED_PARTS)})")
        if folder is None or not (folder / spec.file).is_file():
            log.warning("skipping %s: ../shared/data/parts/%s not found", name, spec.file)
            continue
        mesh, unit = load_mesh(folder / spec.file, spec.unit)
        # The symmetry axes pass through the centre of the part's bounding box.
        symmetry = spec.symmetry.model_copy(update={"origin_m": tuple(float(c) for c in mesh.bounds.mean(axis=0))})
        models.append(make_part_model(name, mesh, symmetry, n_points, rng, unit))
    return models
