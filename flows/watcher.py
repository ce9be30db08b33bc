"""The watcher: every part in data/parts/ gets an up-to-date, evaluated model without anyone
touching anything. New mesh files are added to params.yaml (files whose names cannot be used are
refused, named in the summary); each part whose DVC stages are not up to date runs the training
flow; a part that fails is set aside until its mesh or entry changes, and the others go on.
Then each trained part whose approved real captures (flows/learn.py) reach learn.min_new_scenes
new ones is fine-tuned on them, and served only when no worse."""

import json
import logging
import subprocess
import sys
from pathlib import Path

from prefect import flow, task
from prefect.logging import get_run_logger

from binpick.io.mesh import MESH_SUFFIXES
from binpick.layout import Layout
from binpick.params import add_parts, load_raw
from binpick.project import check_project, set_aside
from flows.dvc_tasks import StageFailed, dvc_env
from flows.pipeline import PART_STAGES, Outcome, new_files, train_part

log = logging.getLogger("binpick.watch")


@task(name="add-new-parts")
def add_new_parts(root: Path) -> tuple[list[str], dict[str, str]]:
    """Mesh files in data/parts/ that no part lists are added to params.yaml (unit: auto).
    Returns (names added, refused file -> reason)."""
    raw = load_raw(root / "params.yaml")
    listed = {Path(p["mesh"]).as_posix(): name for name, p in (raw.get("parts") or {}).items()}
    _, new, refused = new_files(
        root, Layout(root).parts_folder, set(MESH_SUFFIXES), listed, set(raw.get("parts") or {})
    )
    if new:
        add_parts(root / "params.yaml", new)
        log.info("new parts: %s", ", ".join(f"{k} ({v})" for k, v in new.items()))
    return sorted(new), refused


@task(name="stale-parts")
def stale_parts(root: Path, parts: list[str]) -> list[str]:
    """Parts whose stages (or anything they depend on) are not up to date in DVC."""
    stale = []
    for part in parts:
        targets = [f"{stage}@{part}" for stage in PART_STAGES]
        proc = subprocess.run(
            [sys.executable, "-m", "dvc", "status", "--with-deps", "--json", *targets],
            cwd=root,
            env=dvc_env(),
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise StageFailed(f"dvc status {part}", (proc.stderr.strip().splitlines() or ["no output"])[-1])
        if json.loads(proc.stdout or "{}"):
            stale.append(part)
    return stale


def unit_note(root: Path, part: str) -> str | None:
    """'unit guessed: mm' for a part whose unit is `auto`, from its ingest metrics."""
    entry = (load_raw(root / "params.yaml").get("parts") or {}).get(part) or {}
    path = Layout(root).part_metrics(part, "ingest")
    if entry.get("unit", "auto") != "auto" or not path.is_file():
        return None
    unit = json.loads(path.read_text()).get("unit")
    return f"unit guessed: {unit}" if unit else None


@task(name="finetune-part")
def finetune_part(root: Path, part: str) -> str | None:
    """Fine-tune the part on its approved real captures when enough are new; what happened, in
    words, or None when it waits for more."""
    from binpick.errors import BinpickError
    from binpick.params import load_params
    from flows.learn import finetune

    try:
        result = finetune(root, load_params(root / "params.yaml", part), part, progress=False)
    except BinpickError as exc:
        return f"fine-tuning failed: {exc}"
    if not result["finetuned"]:
        return None
    return (
        f"fine-tuned on {result['n_train_real']} real captures: "
        f"{'served' if result['served'] else 'worse, not served'} "
        f"(held-back real P/R {result['after_real_precision']:.2f}/{result['after_real_recall']:.2f}, "
        f"before {result['before_real_precision']:.2f}/{result['before_real_recall']:.2f})"
    )


@flow(name="watch-parts", flow_run_name="watch-parts")
def watch_parts(root: Path) -> Outcome:
    """Register new parts, then train and evaluate each part that is not up to date."""
    root = Path(root)
    added, refused = add_new_parts(root)
    plan = check_project(root)
    outcome = Outcome(added=added, refused=refused, set_aside={n: e.reason for n, e in plan.set_aside["parts"].items()})
    for part in stale_parts(root, sorted(plan.pipeline.parts)):
        try:
            train_part(part, root)
            outcome.ran.append(part)
        except StageFailed as exc:
            outcome.failed[part] = exc.reason
            set_aside(root, "parts", part, exc.reason)
    for part in outcome.added + outcome.ran:
        note = unit_note(root, part)
        if note:
            outcome.notes[part] = note
    for part in sorted(plan.pipeline.parts):
        if part not in outcome.failed and Layout(root).checkpoint(part).is_file():
            learnt = finetune_part(root, part)
            if learnt:
                outcome.notes[part] = "; ".join(filter(None, [outcome.notes.get(part), learnt]))
    get_run_logger().info("%s", outcome.summary("trained"))
    return outcome
