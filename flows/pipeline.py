"""The pipeline as Prefect flows: train a part, process a capture, and the end-to-end demo."""

from __future__ import annotations

import json
from pathlib import Path

from prefect import flow

from flows.dvc_tasks import repro_stage

PART_STAGES = ("ingest", "ppf", "generate", "train", "evaluate")
SCENE_STAGES = ("import_scene", "segment", "register")


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


def read_metrics(root: Path, *parts: str) -> dict[str, float]:
    path = root.joinpath("data", "metrics", *parts)
    return json.loads(path.read_text()) if path.is_file() else {}


@flow(name="demo", flow_run_name="demo")
def demo(root: Path, part: str = "t_joint", capture: str = "demo") -> dict[str, dict[str, float]]:
    """The main job on the built-in part: train it, render a demo capture, process the capture."""
    train_part(part, root)
    repro_stage("demo_capture", root)
    process_capture(capture, root)
    return {
        "evaluate": read_metrics(root, part, "evaluate.json"),
        "train": read_metrics(root, part, "train.json"),
        "register": read_metrics(root, "scenes", capture, "register.json"),
        "segment": read_metrics(root, "scenes", capture, "segment.json"),
        "import": read_metrics(root, "scenes", capture, "import.json"),
    }
