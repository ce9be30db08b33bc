"""dvc.yaml spells the data/ layout for DVC; binpick.layout owns it for Python. They must agree."""

from __future__ import annotations

from pathlib import Path

import yaml

from binpick.layout import Layout

ROOT = Path(__file__).resolve().parents[1]
PART, CAPTURE = "sample_part", "sample_capture"
ITEM = {
    "mesh": "data/parts/sample_part.stl",
    "grasps": "",
    "grasps_dep": "data/parts/sample_part.stl",
    "distractors": "",
    "distractors_dep": "data/parts/sample_part.stl",
    "part": PART,
    "file": "data/captures/c.ply",
    "truth": "",
    "truth_dep": "data/captures/c.ply",
    "intrinsics": "",
    "intrinsics_dep": "data/captures/c.ply",
}


def _render(value: str, key: str) -> str:
    value = value.replace("${key}", key)
    for name, v in ITEM.items():
        value = value.replace(f"${{item.{name}}}", v)
    return value


def _stage_files(stage: dict, key: str) -> tuple[set[str], set[str]]:
    """(outs and metrics, data/ deps) of one foreach stage rendered for `key`."""
    do = stage["do"]
    outs = {
        _render(o if isinstance(o, str) else next(iter(o)), key) for o in do.get("outs", []) + do.get("metrics", [])
    }
    deps = {_render(d, key) for d in do.get("deps", []) if d.startswith(("data/", "${item"))}
    return outs, {d for d in deps if d.startswith("data/") and not d.startswith(("data/parts/", "data/captures/"))}


def test_dvc_outs_are_the_layout_paths():
    L = Layout(Path("."))
    rel = lambda p: p.as_posix()  # noqa: E731 - a renaming, not logic
    expected = {
        "ingest": {L.part_model(PART), L.part_metrics(PART, "ingest")},
        "ppf": {L.ppf_model(PART), L.part_metrics(PART, "ppf")},
        "grasps": {L.grasps(PART), L.grasps_recording(PART), L.part_metrics(PART, "grasps")},
        "generate": {L.scenes(PART), L.part_metrics(PART, "generate")},
        "train": {L.checkpoint(PART), L.part_metrics(PART, "train")},
        "evaluate": {L.part_metrics(PART, "evaluate")},
        "import_capture": {L.cloud(CAPTURE), L.scene_metrics(CAPTURE, "import")},
        "segment": {L.segments(CAPTURE), L.scene_metrics(CAPTURE, "segment")},
        "register": {L.poses(CAPTURE), L.scene_recording(CAPTURE), L.scene_metrics(CAPTURE, "register")},
        "label": {L.labelled_capture(PART, CAPTURE), L.scene_metrics(CAPTURE, "label")},
        "pick": {L.picks(CAPTURE), L.picks_recording(CAPTURE), L.scene_metrics(CAPTURE, "pick")},
        "mixed": {L.picks(CAPTURE), L.scene_metrics(CAPTURE, "mixed")},
    }
    if "verify" in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]:
        expected["verify"] = {L.verification(PART), L.part_metrics(PART, "verify")}
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    every_layout_path = {rel(p) for paths in expected.values() for p in paths}
    every_layout_path |= {rel(L.models_folder), rel(L.networks_folder)}  # a mixed capture's deps
    per_part = {s for s in stages if "foreach" in stages[s] and stages[s]["foreach"] == "${stage_parts}"}
    assert set(expected) == {s for s in stages if "foreach" in stages[s]}
    for name, paths in expected.items():
        outs, deps = _stage_files(stages[name], PART if name in per_part else CAPTURE)
        assert outs == {rel(p) for p in paths}, name
        assert deps <= every_layout_path, (name, deps - every_layout_path)


def test_layout_is_under_the_root(tmp_path):
    L = Layout(tmp_path)
    for path in (
        L.checkpoint("p"),
        L.poses("c"),
        L.labelled_capture("p", "c"),
        L.pipeline_vars,
        L.scene_metrics("c", "pick"),
    ):
        assert path.is_relative_to(tmp_path / "data")
