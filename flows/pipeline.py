"""The pipeline as Prefect flows: train a part, process a capture, and the end-to-end demo."""


import json
from pathlib import Path

from prefect import flow, task
from prefect.logging import get_run_logger

from binpick.errors import InputError
from binpick.io.capture import CAPTURE_SUFFIXES
from binpick.params import add_captures, load_raw, part_name_for
from flows.dvc_tasks import repro_stage

PART_STAGES = ("ingest", "ppf", "generate", "train", "evaluate")
SCENE_STAGES = ("import_capture", "segment", "register")


@flow(name="train-part", flow_run_name="train-{part}")
def train_part(part: str, root: Path) -> None:
    """ingest -> ppf -> generate -> train -> evaluate, each the part's DVC stage."""
    for stage in PART_STAGES:
        repro_stage(f"{stage}@{part}", root)


@flow(name="scene", flow_run_name="scene-{capture}")
def process_capture(capture: str, root: Path) -> None:
    """import (+ plane filter) -> segment -> register for one capture listed in params.yaml."""
    for stage in SCENE_STAGES:
        repro_stage(f"{stage}@{capture}", root)


@task(name="add-new-captures")
def add_new_captures(root: Path, folder: Path, part: str, unit: str) -> list[str]:
    """The captures in `folder` (inside the project), as names in params.yaml: files no capture
    lists yet are added for `part` in `unit`. Depth images are skipped (they need intrinsics,
    which an entry in params.yaml gives)."""
    folder = (root / folder).resolve()
    if not folder.is_dir():
        raise InputError(folder, "not a folder of captures")
    if not folder.is_relative_to(root):
        raise InputError(folder, f"captures must lie inside the project {root} (DVC tracks them by relative path)")
    raw = load_raw(root / "params.yaml")
    listed = {Path(c["file"]).as_posix(): name for name, c in (raw.get("captures") or {}).items()}
    names, new = [], {}
    for path in sorted(folder.iterdir()):
        rel = path.relative_to(root).as_posix()
        if path.suffix.lower() not in CAPTURE_SUFFIXES or path.suffix.lower() == ".png":
            continue
        if rel in listed:
            names.append(listed[rel])
            continue
        name = part_name_for(path)
        while name in listed.values() or name in new:
            name += "_new"
        new[name] = rel
        names.append(name)
    if new:
        add_captures(root / "params.yaml", new, part, unit)
        get_run_logger().info("new captures: %s", ", ".join(f"{k} ({v})" for k, v in new.items()))
    return names


@flow(name="scenes", flow_run_name="scenes-{part}")
def process_folder(root: Path, folder: Path, part: str, unit: str = "mm") -> dict[str, dict[str, float]]:
    """Every capture in a folder: listed in params.yaml if new, then imported, segmented and
    registered (captures already processed with unchanged inputs are skipped by DVC)."""
    root = Path(root).resolve()
    names = add_new_captures(root, Path(folder), part, unit)
    if not names:
        raise InputError(folder, f"holds no captures ({', '.join(s for s in CAPTURE_SUFFIXES if s != '.png')})")
    for name in names:
        process_capture(name, root)
    return {name: read_metrics(root, "scenes", name, "register.json") for name in names}


def read_metrics(root: Path, *parts: str) -> dict[str, float]:
    path = root.joinpath("data", "metrics", *parts)
    return json.loads(path.read_text()) if path.is_file() else {}


@flow(name="demo", flow_run_name="demo")
def demo(root: Path, part: str = "t_joint", capture: str = "demo") -> dict[str, dict[str, float]]:
    """The main job on the built-in part: train it, render a demo capture, process the capture."""
    train_part(part, root)
    repro_stage("render_demo", root)
    process_capture(capture, root)
    return {
        "evaluate": read_metrics(root, part, "evaluate.json"),
        "train": read_metrics(root, part, "train.json"),
        "register": read_metrics(root, "scenes", capture, "register.json"),
        "segment": read_metrics(root, "scenes", capture, "segment.json"),
        "import": read_metrics(root, "scenes", capture, "import.json"),
    }
