"""The pipeline as Prefect flows: train a part, process a capture, and the end-to-end demo.

Every flow checks the project first (`binpick.project.check_project`: params.yaml valid as a
whole, names and paths safe, data/pipeline.yaml current). A part or capture whose stage fails is
set aside (data/set_aside.yaml) and the others go on; the flow's result says what failed and why.
"""

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from prefect import flow, task

from binpick.errors import InputError
from binpick.io.capture import CAPTURE_SUFFIXES
from binpick.layout import Layout
from binpick.params import add_captures, check_project_path, load_raw, part_name_for
from binpick.project import check_project, set_aside
from flows.dvc_tasks import StageFailed, repro_stage

log = logging.getLogger("binpick.flows")
PART_STAGES = ("ingest", "ppf", "grasps", "generate", "train", "verify", "evaluate")
SCENE_STAGES = ("import_capture", "segment", "register", "label", "pick")


@dataclass
class Outcome:
    """What a flow over many parts or captures did: names added, run, failed (with the stage's
    error line), refused files (with the reason) and entries still set aside from earlier runs."""

    added: list[str] = field(default_factory=list)
    ran: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    refused: dict[str, str] = field(default_factory=dict)
    set_aside: dict[str, str] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)

    def summary(self, ran_word: str) -> str:
        def names(items: list[str]) -> str:
            return ", ".join(f"{n} ({self.notes[n]})" if n in self.notes else n for n in items) or "none"

        parts = [f"added: {names(self.added)}", f"{ran_word}: {names(self.ran)}"]
        if self.failed:
            parts.append("failed, set aside: " + "; ".join(f"{n} ({why})" for n, why in self.failed.items()))
        if self.set_aside:
            parts.append("still set aside: " + "; ".join(f"{n} ({why})" for n, why in self.set_aside.items()))
        if self.refused:
            parts.append("refused: " + "; ".join(f"{n} ({why})" for n, why in self.refused.items()))
        return "; ".join(parts)


def safe_file_name(root: Path, path: Path) -> str | None:
    """Why `path` (a file found in the project) cannot be used, or None when it can."""
    rel = path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path)
    try:
        check_project_path(rel, "file")
    except ValueError as exc:
        return f"{exc}; rename it"
    if not path.resolve().is_relative_to(root.resolve()):
        return "a link to a file outside the project; copy the file in instead"
    return None


def new_files(
    root: Path, folder: Path, suffixes: set[str], listed: dict[str, str], taken: set[str]
) -> tuple[list[str], dict[str, str], dict[str, str]]:
    """The files in `folder` with one of `suffixes` (lower case), as params.yaml names: those
    `listed` (relative path -> name) keep theirs; a new one gets a name from its file name, made
    unique against `taken` and each other; files whose names cannot reach a command are refused.
    Returns (every name in the folder, new name -> relative path, refused file -> reason)."""
    names: list[str] = []
    new: dict[str, str] = {}
    refused: dict[str, str] = {}
    for path in sorted(folder.iterdir()):
        rel = path.relative_to(root).as_posix()
        if path.suffix.lower() not in suffixes:
            continue
        if rel in listed:
            names.append(listed[rel])
            continue
        why = safe_file_name(root, path)
        if why:
            refused[rel] = why
            continue
        name = part_name_for(path)
        while name in taken or name in new:
            name += "_new"
        new[name] = rel
        names.append(name)
    return names, new, refused


@flow(name="train-part", flow_run_name="train-{part}")
def train_part(part: str, root: Path) -> None:
    """ingest -> ppf -> grasps -> generate -> train -> evaluate, each the part's DVC stage."""
    for stage in PART_STAGES:
        repro_stage(f"{stage}@{part}", root)


@flow(name="scene", flow_run_name="scene-{capture}")
def process_capture(capture: str, root: Path) -> None:
    """import (+ plane filter) -> segment -> register -> label (learning from the cell) -> pick for
    one capture listed in params.yaml."""
    for stage in SCENE_STAGES:
        repro_stage(f"{stage}@{capture}", root)


@task(name="add-new-captures")
def add_new_captures(root: Path, folder: Path, part: str, unit: str) -> tuple[list[str], list[str], dict[str, str]]:
    """The captures in `folder` (inside the project), as names in params.yaml: files no capture
    lists yet are added for `part` in `unit`. Depth images are skipped (they need intrinsics,
    which an entry in params.yaml gives); files whose names cannot reach a command are refused.
    Returns (all names in the folder, the names added, refused file -> reason)."""
    folder = (root / folder).resolve()
    if not folder.is_dir():
        raise InputError(folder, "not a folder of captures")
    if not folder.is_relative_to(root):
        raise InputError(folder, f"captures must lie inside the project {root} (DVC tracks them by relative path)")
    raw = load_raw(root / "params.yaml")
    if part not in (raw.get("parts") or {}):
        raise InputError(
            root / "params.yaml", f"part {part!r} is not listed under 'parts' (have: {sorted(raw.get('parts') or {})})"
        )
    listed = {Path(c["file"]).as_posix(): name for name, c in (raw.get("captures") or {}).items()}
    names, new, refused = new_files(
        root, folder, set(CAPTURE_SUFFIXES) - {".png"}, listed, set(raw.get("captures") or {})
    )
    if new:
        add_captures(root / "params.yaml", new, part, unit)
        log.info("new captures: %s", ", ".join(f"{k} ({v})" for k, v in new.items()))
    return names, sorted(new), refused


@flow(name="scenes", flow_run_name="scenes-{part}")
def process_folder(
    root: Path, folder: Path, part: str, unit: str = "mm"
) -> tuple[Outcome, dict[str, dict[str, float]]]:
    """Every capture in a folder: listed in params.yaml if new, then imported, segmented and
    registered (captures already processed with unchanged inputs are skipped by DVC). A capture
    that fails is set aside and the others go on."""
    root = Path(root).resolve()
    names, added, refused = add_new_captures(root, Path(folder), part, unit)
    if not names and not refused:
        raise InputError(folder, f"holds no captures ({', '.join(s for s in CAPTURE_SUFFIXES if s != '.png')})")
    plan = check_project(root)
    outcome = Outcome(added=added, refused=refused)
    for name in names:
        if name in plan.set_aside["captures"]:
            outcome.set_aside[name] = plan.set_aside["captures"][name].reason
            continue
        if name not in plan.pipeline.captures:  # its part is set aside
            outcome.set_aside[name] = f"its part {plan.params.captures[name].part} is set aside"
            continue
        try:
            process_capture(name, root)
            outcome.ran.append(name)
        except StageFailed as exc:
            outcome.failed[name] = exc.reason
            set_aside(root, "captures", name, exc.reason)
    return outcome, {name: read_metrics(Layout(root).scene_metrics(name, "register")) for name in outcome.ran}


def read_metrics(path: Path) -> dict[str, float]:
    return json.loads(path.read_text()) if path.is_file() else {}


@flow(name="demo", flow_run_name="demo")
def demo(root: Path, part: str = "t_joint", capture: str = "demo") -> dict[str, dict[str, float]]:
    """The main job on the built-in part: train it, render a demo capture, process the capture."""
    check_project(Path(root))
    train_part(part, root)
    repro_stage("render_demo", root)
    process_capture(capture, root)
    layout = Layout(root)
    return {
        **{stage: read_metrics(layout.part_metrics(part, stage)) for stage in ("evaluate", "train")},
        **{
            stage: read_metrics(layout.scene_metrics(capture, stage))
            for stage in ("register", "segment", "import", "pick")
        },
    }
