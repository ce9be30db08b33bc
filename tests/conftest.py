"""Shared fixtures. Real third-party data is read from ../shared/data beside the project and
tests that need it skip, saying so, when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from binpick.env import configure_environment

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

configure_environment(ROOT)
os.environ.setdefault("TQDM_DISABLE", "1")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "MANIFEST.md").is_file():
        pytest.skip(f"real third-party data not found at {SHARED_DATA} (it lives beside the project, not in it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def t_joint():
    """The built-in part as a part model (metres)."""
    from binpick.part.model import DEFAULT_PART_NAME, T_JOINT_SYMMETRY, build_t_joint_mesh, make_part_model

    mesh = build_t_joint_mesh()
    mesh.apply_scale(1e-3)
    return make_part_model(DEFAULT_PART_NAME, mesh, T_JOINT_SYMMETRY, 20000, np.random.default_rng(0), "mm")


@pytest.fixture(scope="session")
def params():
    from binpick.params import load_params

    return load_params(ROOT / "params.yaml", "t_joint")


@pytest.fixture(scope="session")
def pick_settings(params):
    """The pick section of the project's params (t_joint resolved)."""
    return params.pick


def box_part_model(extents_m):
    """A box part of these extents (3,), metres, model frame at its centre, no symmetry."""
    import trimesh

    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model

    return make_part_model(
        "box", trimesh.creation.box(extents=extents_m), SymmetryParams(), 20000, np.random.default_rng(0), "m"
    )


def copy_project(root: Path, params_text: str | None = None) -> Path:
    """A copy of the project's code, pipeline and built-in part in `root` (a git repository), with
    params.yaml's text (default: the project's own), for tests that run the real entry points."""
    import shutil
    import subprocess

    for name in ("binpick", "stages", "flows", "review", ".dvc"):
        shutil.copytree(
            ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__", "tmp", "cache", "config.local")
        )
    for name in ("dvc.yaml", "pyproject.toml", ".gitignore", ".dvcignore"):
        shutil.copy(ROOT / name, root / name)
    (root / "data" / "parts").mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "data" / "parts" / "t_joint.stl", root / "data" / "parts")
    (root / "params.yaml").write_text(params_text if params_text is not None else (ROOT / "params.yaml").read_text())
    subprocess.run(["git", "init", "-q"], cwd=root, check=True)
    return root
