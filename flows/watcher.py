"""The watcher: every part in data/parts/ gets an up-to-date, evaluated model without anyone
touching anything. New mesh files are added to params.yaml; each part whose DVC stages are not
up to date runs the training flow; up-to-date parts are skipped."""


import json
import subprocess
import sys
from pathlib import Path

from prefect import flow, task
from prefect.logging import get_run_logger

from binpick.io.mesh import MESH_SUFFIXES
from binpick.params import add_parts, load_raw, part_name_for
from flows.dvc_tasks import StageFailed, dvc_env
from flows.pipeline import PART_STAGES, train_part

PARTS_FOLDER = Path("data") / "parts"


@task(name="add-new-parts")
def add_new_parts(root: Path) -> list[str]:
    """Mesh files in data/parts/ that no part lists are added to params.yaml (unit: auto)."""
    raw = load_raw(root / "params.yaml")
    listed = {Path(p["mesh"]).as_posix() for p in (raw.get("parts") or {}).values()}
    names = set(raw.get("parts") or {})
    new: dict[str, str] = {}
    for mesh in sorted((root / PARTS_FOLDER).iterdir()):
        rel = mesh.relative_to(root).as_posix()
        if mesh.suffix.lower() not in MESH_SUFFIXES or rel in listed:
            continue
        name = part_name_for(mesh)
        while name in names or name in new:
            name += "_new"
        new[name] = rel
    if new:
        add_parts(root / "params.yaml", new)
        get_run_logger().info("new parts: %s", ", ".join(f"{k} ({v})" for k, v in new.items()))
    return sorted(new)


@task(name="stale-parts")
def stale_parts(root: Path) -> list[str]:
    """Parts whose stages (or anything they depend on) are not up to date in DVC."""
    parts = sorted(load_raw(root / "params.yaml").get("parts") or {})
    stale = []
    for part in parts:
        targets = [f"{stage}@{part}" for stage in PART_STAGES]
        proc = subprocess.run(
            [sys.executable, "-m", "dvc", "status", "--with-deps", "--json", *targets],
            cwd=root, env=dvc_env(), capture_output=True, text=True,
        )
        if proc.returncode != 0:
            raise StageFailed(f"dvc status for {part} failed: {proc.stderr.strip().splitlines()[-1:]}")
        if json.loads(proc.stdout or "{}"):
            stale.append(part)
    return stale


@flow(name="watch-parts", flow_run_name="watch-parts")
def watch_parts(root: Path) -> dict[str, list[str]]:
    """Register new parts, then train and evaluate each part that is not up to date."""
    root = Path(root)
    added = add_new_parts(root)
    stale = stale_parts(root)
    logger = get_run_logger()
    for part in stale:
        train_part(part, root)
    logger.info("trained: %s; up to date: %s", stale or "none", sorted(set(load_raw(root / "params.yaml")["parts"]) - set(stale)) or "none")
    return {"added": added, "trained": stale}
