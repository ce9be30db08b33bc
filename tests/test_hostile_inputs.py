"""Hostile but realistic input through the real entry points: names and paths that would run shell
commands if they reached DVC's command lines, and settings files with mistakes anywhere in them.
Each case ends in one clear error line (or a refusal named in a summary), nothing runs, nothing is
half-written."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT, copy_project

HOSTILE = "evil$(touch INJECTED)"


def _run(root, *args):
    return subprocess.run([sys.executable, *args], cwd=root, capture_output=True, text=True, timeout=300)


def _one_error_line(proc, *needles):
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


@pytest.fixture
def project(tmp_path):
    root = copy_project(tmp_path / "project")
    assert _run(root, "-m", "flows.cli", "check").returncode == 0
    return root


def _edit(root: Path, change) -> None:
    raw = yaml.safe_load((root / "params.yaml").read_text())
    change(raw)
    (root / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))


def _no_injection(root: Path, before: str) -> None:
    assert not list(root.rglob("INJECTED")) and not Path("INJECTED").exists()
    assert (root / "data" / "pipeline.yaml").read_text() == before  # DVC still sees the checked names


def _rename_part(raw):
    raw["parts"][HOSTILE] = raw["parts"].pop("t_joint")
    raw["render_demo"]["part"] = HOSTILE
    raw["captures"]["demo"]["part"] = HOSTILE


CASES = {
    "part name": (_rename_part, "part name"),
    "capture name": (lambda raw: raw["captures"].__setitem__(HOSTILE, raw["captures"].pop("demo")), "capture name"),
    "mesh path": (lambda raw: raw["parts"]["t_joint"].__setitem__("mesh", f"data/parts/{HOSTILE}.stl"), "mesh path"),
    "mesh outside": (lambda raw: raw["parts"]["t_joint"].__setitem__("mesh", "../outside/part.stl"), "no '..'"),
    "mesh absolute": (lambda raw: raw["parts"]["t_joint"].__setitem__("mesh", "/etc/passwd"), "mesh path"),
    "capture file": (
        lambda raw: raw["captures"]["demo"].__setitem__("file", f"data/captures/{HOSTILE}.ply"),
        "file path",
    ),
    "truth path": (
        lambda raw: raw["captures"]["demo"].__setitem__("truth", "data/x';touch INJECTED;'.json"),
        "truth path",
    ),
    "intrinsics path": (
        lambda raw: raw["captures"]["demo"].__setitem__("intrinsics", "data/`touch INJECTED`.json"),
        "intrinsics path",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_names_and_paths_in_params_never_reach_a_shell(project, case):
    change, needle = CASES[case]
    before = (project / "data" / "pipeline.yaml").read_text()
    _edit(project, change)
    _one_error_line(_run(project, "-m", "flows.cli", "check"), "params.yaml", needle)
    _no_injection(project, before)
    # A stage DVC would start refuses to run on a params.yaml that no longer matches what DVC read.
    proc = subprocess.run(
        [sys.executable, "-m", "stages.ppf", "--part", "t_joint", "--model", "m.npz", "--out", "o.npz"],
        cwd=project,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, "DVC_STAGE": "ppf@t_joint"},
    )
    _one_error_line(proc, "params.yaml")
    _no_injection(project, before)


def test_a_link_out_of_the_project_is_refused(project, tmp_path):
    outside = tmp_path / "elsewhere.stl"
    outside.write_bytes((ROOT / "data/parts/t_joint.stl").read_bytes())
    (project / "data/parts/linked.stl").symlink_to(outside)
    _edit(project, lambda raw: raw["parts"]["t_joint"].__setitem__("mesh", "data/parts/linked.stl"))
    _one_error_line(_run(project, "-m", "flows.cli", "check"), "parts.t_joint.mesh", "outside the project")


def test_the_watcher_refuses_mesh_files_whose_names_would_reach_a_shell(project):
    from flows.watcher import add_new_parts

    (project / "data/parts" / f"{HOSTILE}.stl").write_bytes((ROOT / "data/parts/t_joint.stl").read_bytes())
    (project / "data/parts" / "Bracket Block.stl").write_bytes((ROOT / "data/parts/t_joint.stl").read_bytes())
    before = (project / "params.yaml").read_text()
    added, refused = add_new_parts.fn(project)
    assert added == ["bracket_block"]  # a space is fine: the command lines quote paths
    assert list(refused) == [f"data/parts/{HOSTILE}.stl"] and "rename it" in refused[f"data/parts/{HOSTILE}.stl"]
    assert HOSTILE not in (project / "params.yaml").read_text() and before != (project / "params.yaml").read_text()
    assert _run(project, "-m", "flows.cli", "check").returncode == 0
    assert "bracket_block" in (project / "data/pipeline.yaml").read_text()
    assert not list(project.rglob("INJECTED"))


def test_scenes_refuses_capture_files_whose_names_would_reach_a_shell(project):
    folder = project / "data/captures/monday"
    folder.mkdir(parents=True)
    (folder / f"{HOSTILE}.ply").write_text("ply\n")
    proc = _run(project, "-m", "flows.cli", "scenes", "data/captures/monday", "--part", "t_joint")
    assert proc.returncode == 0, proc.stderr
    assert "refused" in proc.stdout and HOSTILE in proc.stdout and "rename it" in proc.stdout
    assert "Traceback" not in proc.stderr
    assert HOSTILE not in (project / "params.yaml").read_text()
    assert not list(project.rglob("INJECTED"))


SETTINGS_MISTAKES = {
    "misspelt section": (
        lambda raw: raw.__setitem__("trian", {"epochs": 3}),
        "unknown top-level key 'trian' (did you mean 'train'?)",
    ),
    "misspelt orchestration key": (lambda raw: raw["orchestration"].__setitem__("worker", 2), "orchestration.worker"),
    "bad value under an override": (lambda raw: raw["generate"].__setitem__("n_train", -5), "generate.n_train"),
    "capture of an unknown part": (
        lambda raw: raw["captures"]["demo"].__setitem__("part", "gear"),
        "names part 'gear'",
    ),
    "negative seed": (lambda raw: raw.__setitem__("seed", -1), "seed"),
    "typo in a part override": (
        lambda raw: raw["parts"]["t_joint"].__setitem__("train", {"epoch": 3}),
        "parts.t_joint: train.epoch",
    ),
    "misspelt profile section": (
        lambda raw: raw["profiles"]["quick"].__setitem__("trian", {}),
        "profiles.quick: 'trian'",
    ),
    "bad value in another profile": (
        lambda raw: raw["profiles"]["cpu"]["train"].__setitem__("epochs", 0),
        "profiles.cpu: train.epochs",
    ),
}


@pytest.mark.parametrize("case", sorted(SETTINGS_MISTAKES))
def test_the_whole_settings_file_is_validated(project, case):
    change, needle = SETTINGS_MISTAKES[case]
    _edit(project, change)
    _one_error_line(_run(project, "-m", "flows.cli", "check"), needle)
    # The stages validate the whole file too, whatever part of it they read.
    proc = _run(
        project,
        "-m",
        "stages.ingest",
        "--part",
        "t_joint",
        "--mesh",
        "data/parts/t_joint.stl",
        "--out",
        "data/models/x/part.npz",
    )
    _one_error_line(proc, needle)
    assert not (project / "data/models/x").exists()


@pytest.mark.slow
def test_a_failing_capture_is_set_aside_and_blocks_nothing(project):
    """A capture whose import fails is set aside: reported with its stage's own error line, left out
    of the pipeline DVC sees, not retried until the file changes, and no traceback is shown."""
    folder = project / "data/captures/monday"
    folder.mkdir(parents=True)
    (folder / "bin_a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n")
    first = _run(project, "-m", "flows.cli", "scenes", "data/captures/monday", "--part", "t_joint")
    assert first.returncode == 1, first.stdout + first.stderr
    assert "Traceback" not in first.stdout + first.stderr
    assert "failed, set aside: bin_a (data/captures/monday/bin_a.ply:" in first.stdout
    assert "bin_a" not in yaml.safe_load((project / "data/pipeline.yaml").read_text())["stage_captures"]
    assert "bin_a" in yaml.safe_load((project / "data/set_aside.yaml").read_text())["captures"]
    status = subprocess.run(
        [sys.executable, "-m", "dvc", "status", "import_capture@demo"], cwd=project, capture_output=True, text=True
    )
    assert status.returncode == 0, status.stderr  # the rest of the pipeline still parses and runs
    second = _run(project, "-m", "flows.cli", "scenes", "data/captures/monday", "--part", "t_joint")
    assert second.returncode == 0 and "still set aside: bin_a" in second.stdout, second.stdout + second.stderr
    # A changed file is tried again.
    (folder / "bin_a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n")
    third = _run(project, "-m", "flows.cli", "scenes", "data/captures/monday", "--part", "t_joint")
    assert "failed, set aside: bin_a" in third.stdout, third.stdout + third.stderr


def test_truth_and_intrinsics_files_are_dependencies(project):
    """Editing a capture's intrinsics or truth file makes its stages stale: both are deps, and an
    entry without them (as the README writes it) still resolves."""

    from dvc.repo import Repo

    (project / "data/captures/cam").mkdir(parents=True)
    (project / "data/captures/cam/depth.png").write_bytes(b"")
    (project / "data/captures/cam/k.json").write_text('{"fx": 1, "fy": 1, "cx": 0, "cy": 0}')
    (project / "data/captures/cam/truth.json").write_text("{}")

    def add(raw):
        raw["captures"]["cam"] = {
            "file": "data/captures/cam/depth.png",
            "part": "t_joint",
            "intrinsics": "data/captures/cam/k.json",
            "truth": "data/captures/cam/truth.json",
        }
        raw["captures"]["bare"] = {"file": "data/captures/cam/depth.png", "part": "t_joint"}

    _edit(project, add)
    assert _run(project, "-m", "flows.cli", "check").returncode == 0
    with Repo(str(project)) as repo:
        deps = {s.addressing.split(":")[-1]: {str(Path(d.def_path)) for d in s.deps} for s in repo.index.stages}
    assert "data/captures/cam/k.json" in deps["import_capture@cam"]
    assert "data/captures/cam/truth.json" in deps["register@cam"]
    assert "data/captures/cam/depth.png" in deps["import_capture@bare"] and "register@bare" in deps
