"""The project as the pipeline sees it: which parts and captures run, checked before DVC sees them.

`check_project` validates params.yaml as a whole, refuses paths that leave the project, leaves out
what was set aside after a failure (until its files or entry change) and writes the DVC variables
file (`binpick.io.pipeline_vars`). Every project command runs it before DVC; every stage checks
at start that the variables file still matches params.yaml.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

from binpick.errors import ParamsError
from binpick.io.atomic import write_text
from binpick.io.digest import file_sha256
from binpick.io.pipeline_vars import (
    PIPELINE_VARS,
    OtherPart,
    PipelineVars,
    SetAside,
    StageCapture,
    StageMixedCapture,
    StagePart,
    distractors_text,
    load_set_aside,
    read_pipeline_vars_text,
    save_set_aside,
    write_pipeline_vars,
)
from binpick.layout import Layout
from binpick.params import Params, load_params

log = logging.getLogger(__name__)

# Where render_demo writes when params.yaml lists no `demo` capture.
DEFAULT_DEMO_FILE = "data/captures/demo/capture.ply"
DEFAULT_DEMO_TRUTH = "data/captures/demo/truth.json"


@dataclass(frozen=True)
class ProjectCheck:
    params: Params
    pipeline: PipelineVars
    set_aside: dict[str, dict[str, SetAside]]  # only the entries still in force
    vars_changed: bool


def fingerprint(root: Path, kind: str, name: str, params: Params) -> str:
    """SHA-256 of a part's or capture's params entry and of every file it names."""
    entry = (params.parts if kind == "parts" else params.captures)[name]
    files = [entry.mesh, entry.grasps] if kind == "parts" else [entry.file, entry.truth, entry.intrinsics]  # type: ignore[union-attr]
    h = hashlib.sha256(json.dumps(entry.model_dump(by_alias=True), sort_keys=True).encode())
    for rel in files:
        if rel:
            digest = file_sha256(root / rel) if (root / rel).is_file() else "missing"
            h.update(f"\0{rel}\0{digest}".encode())
    return h.hexdigest()


def other_parts(root: Path, params: Params, part: str) -> list[OtherPart]:
    """The other parts the part's training scenes mix in (its generate.clutter.parts, without
    itself), each with the fingerprint of its entry and mesh."""
    named = load_params(root / "params.yaml", part).generate.clutter.parts
    return [OtherPart(n, params.parts[n].mesh, fingerprint(root, "parts", n, params)) for n in named if n != part]


def _inside(root: Path, rel: str, where: str) -> None:
    if not (root / rel).resolve().is_relative_to(root.resolve()):
        raise ParamsError(f"{where}: {rel} resolves outside the project {root} (through a link)")


def plan_pipeline(root: Path, params: Params) -> tuple[PipelineVars, dict[str, dict[str, SetAside]]]:
    """The parts and captures that run, and the set-aside entries still in force (same fingerprint)."""
    for name, part in params.parts.items():
        _inside(root, part.mesh, f"parts.{name}.mesh")
        if part.grasps:
            _inside(root, part.grasps, f"parts.{name}.grasps")
    for name, capture in params.captures.items():
        for key in ("file", "truth", "intrinsics"):
            if getattr(capture, key):
                _inside(root, getattr(capture, key), f"captures.{name}.{key}")
    recorded = load_set_aside(root)
    in_force = {
        kind: {
            n: e
            for n, e in recorded[kind].items()
            if n in (params.parts if kind == "parts" else params.captures)
            and e.fingerprint == fingerprint(root, kind, n, params)
        }
        for kind in recorded
    }
    parts = {
        n: StagePart(p.mesh, p.grasps, Layout(Path()).distractors(n).as_posix() if other_parts(root, params, n) else "")
        for n, p in params.parts.items()
        if n not in in_force["parts"]
    }
    captures = {
        n: StageCapture(c.file, c.part, c.truth, c.intrinsics)
        for n, c in params.captures.items()
        if n not in in_force["captures"] and c.part in parts
    }
    # A mixed bin runs once every part of it runs.
    mixed = {
        n: StageMixedCapture(c.file, tuple(c.parts), c.intrinsics)
        for n, c in params.captures.items()
        if c.parts and n not in in_force["captures"] and all(p in parts for p in c.parts)
    }
    demo = params.captures.get("demo")
    pipeline = PipelineVars(
        parts,
        captures,
        params.render_demo.part,
        demo.file if demo else DEFAULT_DEMO_FILE,
        (demo.truth or DEFAULT_DEMO_TRUTH) if demo else DEFAULT_DEMO_TRUTH,
        mixed,
    )
    return pipeline, in_force


def check_project(root: Path, write: bool = True) -> ProjectCheck:
    """Validate params.yaml whole, plan the pipeline and (re)write data/pipeline.yaml.

    Raises ParamsError / InputError with one line; nothing is written then.
    """
    root = Path(root)
    params = load_params(root / "params.yaml")
    pipeline, in_force = plan_pipeline(root, params)
    changed = write_pipeline_vars(root, pipeline) if write else pipeline.as_yaml() != read_pipeline_vars_text(root)
    for name, part in pipeline.parts.items():
        if part.distractors:
            text = distractors_text(name, other_parts(root, params, name))
            path = root / part.distractors
            if not path.is_file() or path.read_text() != text:
                changed = True
                if write:
                    write_text(path, text)
    for kind, entries in in_force.items():
        for name, entry in entries.items():
            log.warning("%s.%s is set aside (%s): fix its file or entry to retry it", kind, name, entry.reason)
    return ProjectCheck(params, pipeline, in_force, changed)


def verify_pipeline_vars(root: Path) -> None:
    """Refuse to run a stage when data/pipeline.yaml no longer matches params.yaml's names and
    paths (params.yaml was edited and `binpick check` not run). Reads no data files: entries left
    out must be listed in the set-aside file."""
    params = load_params(root / "params.yaml")
    try:
        import yaml

        doc = yaml.safe_load(read_pipeline_vars_text(root)) or {}
    except Exception:  # noqa: BLE001 - any damage means: regenerate
        doc = {}
    recorded = load_set_aside(root)
    stage_parts, stage_captures = doc.get("stage_parts") or {}, doc.get("stage_captures") or {}
    planned = {
        n: StagePart(p.mesh, p.grasps, (stage_parts.get(n) or {}).get("distractors", ""))
        for n, p in params.parts.items()
    }
    stale = [n for n in params.parts if stage_parts.get(n) != planned[n].as_vars() and n not in recorded["parts"]]
    # A part that mixes others into its scenes: its list names them as they are now.
    stale += [
        n
        for n, p in planned.items()
        if n in stage_parts
        and (
            bool(p.distractors) != bool(other_parts(root, params, n))
            or (
                p.distractors
                and (
                    not (root / p.distractors).is_file()
                    or (root / p.distractors).read_text() != distractors_text(n, other_parts(root, params, n))
                )
            )
        )
    ]
    stale += [n for n in stage_parts if n not in params.parts]
    stale += [
        n
        for n, c in params.captures.items()
        if c.part
        and (
            (stage_captures.get(n) is None and n not in recorded["captures"] and c.part in stage_parts)
            or (
                n in stage_captures
                and StageCapture(c.file, c.part, c.truth, c.intrinsics).as_vars() != stage_captures[n]
            )
        )
    ]
    stage_mixed = doc.get("stage_mixed") or {}
    stale += [
        n
        for n, c in params.captures.items()
        if c.parts
        and (
            (stage_mixed.get(n) is None and n not in recorded["captures"] and all(p in stage_parts for p in c.parts))
            or (
                n in stage_mixed and StageMixedCapture(c.file, tuple(c.parts), c.intrinsics).as_vars() != stage_mixed[n]
            )
        )
    ]
    stale += [
        n
        for n in [*stage_captures, *stage_mixed]
        if n not in params.captures or bool(params.captures[n].parts) != (n in stage_mixed)
    ]
    if stale or (doc.get("stage_demo") or {}).get("part") != params.render_demo.part:
        raise ParamsError(
            f"{root / PIPELINE_VARS} does not match params.yaml ({', '.join(sorted(stale)) or 'render_demo'}): "
            "run `binpick check` (make repro does), then dvc repro"
        )


def set_aside(root: Path, kind: str, name: str, reason: str) -> None:
    """Keep a failed part or capture out of the pipeline until its files or entry change."""
    params = load_params(root / "params.yaml")
    entries = load_set_aside(root)
    entries[kind][name] = SetAside(
        fingerprint(root, kind, name, params), reason, dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    )
    save_set_aside(root, entries)
    check_project(root)
