"""The pipeline's variables file (`data/pipeline.yaml`) and its set-aside list (`data/set_aside.yaml`).

dvc.yaml iterates over `data/pipeline.yaml`, not over params.yaml: `binpick check` writes it from
params.yaml after validating every name and path, so that DVC, which interpolates names and paths
into shell commands, only ever sees checked text, and so that optional keys of an entry (a
capture's `truth`, `intrinsics`) always exist for DVC. Parts and captures that failed and were set
aside (`data/set_aside.yaml`) are left out of it until their files or entries change.

Spec: data/README.md#pipeline-variables.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from binpick.errors import InputError
from binpick.io.atomic import write_text
from binpick.layout import Layout

# Relative to the project root (the message of a stale variables file names it so).
PIPELINE_VARS = Layout(Path()).pipeline_vars
SET_ASIDE = Layout(Path()).set_aside
KINDS = ("parts", "captures")

_HEADER = (
    "# Written by `binpick check` from params.yaml; do not edit (edit params.yaml, then run\n"
    "# `binpick check`, or `make repro`, which runs it). dvc.yaml iterates over these entries.\n"
)


@dataclass(frozen=True)
class StagePart:
    """A part as the per-part stages see it: its mesh, its grasp file ('' when generated), its
    distractor list (the other parts its training scenes mix in, '' when none) and `grasps_dep`,
    `distractors_dep`, files DVC can always track (the grasp file or the list, else the mesh)."""

    mesh: str
    grasps: str = ""
    distractors: str = ""

    def as_vars(self) -> dict[str, str]:
        return {
            "mesh": self.mesh,
            "grasps": self.grasps,
            "grasps_dep": self.grasps or self.mesh,
            "distractors": self.distractors,
            "distractors_dep": self.distractors or self.mesh,
        }


@dataclass(frozen=True)
class OtherPart:
    """A part another part's training scenes mix in (generate.clutter.parts): its name, mesh and
    the fingerprint of its params entry and mesh (binpick.project.fingerprint)."""

    name: str
    mesh: str
    fingerprint: str


def distractors_text(part: str, others: list[OtherPart]) -> str:
    """The distractor list of a part (data/distractors/<part>.json): DVC tracks this file, so a
    change to another part's mesh or entry makes the part's scenes be generated again."""
    return json.dumps({"part": part, "others": [vars(o) for o in others]}, indent=1) + "\n"


def load_distractors(path: str | Path) -> list[OtherPart]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "distractor list not found (run `binpick check`)")
    try:
        doc = json.loads(path.read_text())
        return [OtherPart(str(o["name"]), str(o["mesh"]), str(o["fingerprint"])) for o in doc["others"]]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"not a distractor list ({type(exc).__name__}: {exc}); run `binpick check`") from None


@dataclass(frozen=True)
class StageCapture:
    """A capture as the scene stages see it. `truth`/`intrinsics` are '' when absent; the `*_dep`
    fields are files DVC can always track: the truth or intrinsics file, else the capture itself."""

    file: str
    part: str
    truth: str
    intrinsics: str

    def as_vars(self) -> dict[str, str]:
        return {
            "file": self.file,
            "part": self.part,
            "truth": self.truth,
            "intrinsics": self.intrinsics,
            "truth_dep": self.truth or self.file,
            "intrinsics_dep": self.intrinsics or self.file,
        }


@dataclass(frozen=True)
class StageMixedCapture:
    """A capture of several kinds of part as the `mixed` stage sees it: `parts` joined by commas
    (DVC interpolates strings only), `intrinsics` '' when absent, `intrinsics_dep` as above."""

    file: str
    parts: tuple[str, ...]
    intrinsics: str

    def as_vars(self) -> dict[str, str]:
        return {
            "file": self.file,
            "parts": ",".join(self.parts),
            "intrinsics": self.intrinsics,
            "intrinsics_dep": self.intrinsics or self.file,
        }


@dataclass(frozen=True)
class PipelineVars:
    parts: dict[str, StagePart]
    captures: dict[str, StageCapture]
    demo_part: str
    demo_file: str
    demo_truth: str
    mixed: dict[str, StageMixedCapture] = field(default_factory=dict)

    def as_yaml(self) -> str:
        doc = {
            "stage_parts": {name: part.as_vars() for name, part in sorted(self.parts.items())},
            "stage_captures": {name: c.as_vars() for name, c in sorted(self.captures.items())},
            "stage_mixed": {name: c.as_vars() for name, c in sorted(self.mixed.items())},
            "stage_demo": {"part": self.demo_part, "file": self.demo_file, "truth": self.demo_truth},
        }
        return _HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)


def read_pipeline_vars_text(root: Path) -> str:
    path = root / PIPELINE_VARS
    return path.read_text() if path.is_file() else ""


def write_pipeline_vars(root: Path, plan: PipelineVars) -> bool:
    """Write data/pipeline.yaml when its content changes; True when it did."""
    text = plan.as_yaml()
    if read_pipeline_vars_text(root) == text:
        return False
    write_text(root / PIPELINE_VARS, text)
    return True


@dataclass(frozen=True)
class SetAside:
    """A part or capture that failed: kept out of the pipeline while `fingerprint` (its files and
    its params entry) is unchanged."""

    fingerprint: str
    reason: str
    when: str


def load_set_aside(root: Path) -> dict[str, dict[str, SetAside]]:
    """{'parts': {name: SetAside}, 'captures': {...}}; empty when the file is absent."""
    path = root / SET_ASIDE
    out: dict[str, dict[str, SetAside]] = {kind: {} for kind in KINDS}
    if not path.is_file():
        return out
    try:
        doc: Any = yaml.safe_load(path.read_text()) or {}
        for kind in KINDS:
            for name, entry in (doc.get(kind) or {}).items():
                out[kind][str(name)] = SetAside(str(entry["fingerprint"]), str(entry["reason"]), str(entry["when"]))
    except (yaml.YAMLError, AttributeError, KeyError, TypeError) as exc:
        raise InputError(
            path, f"not a set-aside list ({type(exc).__name__}: {exc}); delete it to retry everything"
        ) from None
    return out


def save_set_aside(root: Path, entries: dict[str, dict[str, SetAside]]) -> None:
    doc = {kind: {name: vars(e) for name, e in sorted(entries.get(kind, {}).items())} for kind in KINDS}
    write_text(
        root / SET_ASIDE,
        "# Parts and captures that failed, kept out of the pipeline until their files or params\n"
        "# entries change (written by binpick watch / scenes / repro; delete an entry to retry it).\n"
        + yaml.safe_dump(doc, sort_keys=False),
    )
