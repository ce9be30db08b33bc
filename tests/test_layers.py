"""The layers point one way (the library never imports the application or its frameworks), and
every DVC stage depends on all the code it runs."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from layers import ROOT, all_modules, closure, imported_names, module_file

# The library holds kernels and file formats; these belong to the application side.
FORBIDDEN_IN_LIBRARY = ("stages", "flows", "review", "prefect", "mlflow", "rerun", "dvc")


def test_the_library_imports_no_application_module_and_no_framework():
    offences = []
    for name in all_modules("binpick"):
        path = module_file(name)
        for imported in imported_names(path, name):
            if imported.split(".")[0] in FORBIDDEN_IN_LIBRARY:
                offences.append(f"{path.relative_to(ROOT)} imports {imported}")
    assert not offences, "\n".join(offences)


def test_loading_every_library_module_loads_no_framework():
    """The same contract at run time: nothing the static reading missed (an import by name)."""
    code = (
        "import importlib, sys; from layers import all_modules\n"
        "[importlib.import_module(m) for m in all_modules('binpick')]\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({FORBIDDEN_IN_LIBRARY!r})))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT / "tests", capture_output=True, text=True, check=True
    ).stdout
    assert out.strip() == "[]"


def test_the_contract_test_sees_a_violation(tmp_path):
    """The reader finds imports inside functions and relative ones."""
    path = tmp_path / "mod.py"
    path.write_text("def f():\n    import mlflow\n    from ..stages import common\n")
    assert {"mlflow", "binpick.stages", "binpick.stages.common"} <= imported_names(path, "binpick.io.mod")


def _stages() -> list[tuple[str, str, list[str]]]:
    """(DVC stage, stage module, deps) of every stage in dvc.yaml."""
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    out = []
    for name, stage in doc["stages"].items():
        body = stage.get("do", stage)
        cmd = " ".join(body["cmd"].split())
        module = cmd.split("python -m ", 1)[1].split()[0]
        out.append((name, module, body.get("deps", [])))
    return out


@pytest.mark.parametrize(("stage", "module", "deps"), _stages(), ids=[s[0] for s in _stages()])
def test_every_stage_depends_on_the_code_it_imports(stage, module, deps):
    code_deps = [d.rstrip("/") for d in deps if "${" not in d]
    missing = []
    for path in closure(module).values():
        rel = path.relative_to(ROOT).as_posix()
        if not any(rel == d or rel.startswith(d + "/") for d in code_deps):
            missing.append(rel)
    assert not missing, f"dvc.yaml stage {stage!r} runs {module} but does not depend on {missing}"
    for d in code_deps:
        assert (ROOT / d).exists(), f"dvc.yaml stage {stage!r} depends on {d}, which does not exist"


def test_training_depends_on_no_registration_or_picking_code():
    """A change to registration, verification or picking re-runs verify and the scene stages,
    never a network's training (10 minutes to hours a part); picking needs no network."""
    stages = {name: (module, deps) for name, module, deps in _stages()}
    scene_code = (
        "binpick/registration",
        "binpick/picking/plan.py",
        "binpick/scene",
        "binpick/scene/verification_threshold.py",
        "binpick/picking/gripper.py",
    )
    module, deps = stages["train"]
    imported = [p.relative_to(ROOT).as_posix() for p in closure(module).values()]
    assert not [d for d in deps if d.startswith(scene_code)]
    assert not [f for f in imported if f.startswith(scene_code[:-1])]
    module, deps = stages["pick"]
    assert not [
        f for f in (p.relative_to(ROOT).as_posix() for p in closure(module).values()) if f.startswith("binpick/network")
    ]


def test_the_library_starts_no_application_process():
    """`python -m flows ...` or `-m stages ...` from the library would be the application called
    through a back door; the benchmarks that start the service live in flows/bench."""
    import re

    pattern = re.compile(r"""["']-m["']\s*,\s*["'](flows|stages)\b|-m (flows|stages)\.""")
    offences = [
        f"{module_file(name).relative_to(ROOT)}"
        for name in all_modules("binpick")
        if pattern.search(module_file(name).read_text())
    ]
    assert not offences, offences
