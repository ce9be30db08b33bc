"""The whole pipeline through the Prefect demo flow driving DVC, on a copy of the project with a
tiny profile: every stage runs for real, `dvc status` is clean afterwards, a deleted output is
restored by `dvc repro`."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT

TINY = {
    "ingest": {"n_surface_points": 8000},
    "camera": {"downscale": 8},
    "generate": {"n_train": 6, "n_val": 2, "n_test": 2, "workers": 2, "placement": {"n_objects_min": 2, "n_objects_max": 4}},
    "train": {"n_points": 512, "width": 8, "embedding_dim": 8, "k_neighbours": 8, "epochs": 2, "batch_size": 2, "loss_anchors": 128},
    "evaluate": {"accept_precision": 0.0, "accept_recall": 0.0},  # every model is accepted
    "scene_import": {},
    "segment": {"n_points": 512},
    "register": {},
    "demo_capture": {"n_objects": 4, "downscale": 4},
}


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("project")
    for name in ("binpick", "stages", "flows", ".dvc"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__", "tmp", "cache"))
    for name in ("dvc.yaml", "pyproject.toml", ".gitignore"):
        shutil.copy(ROOT / name, root / name)
    (root / "data" / "parts").mkdir(parents=True)
    shutil.copy(ROOT / "data" / "parts" / "t_joint.stl", root / "data" / "parts")
    # Edit the text, so that the copy keeps params.yaml's comments.
    text = (ROOT / "params.yaml").read_text().replace("\nprofile: quick\n", "\nprofile: tiny\n", 1)
    tiny = "".join(f"  {line}\n" for line in yaml.safe_dump({"tiny": TINY}, sort_keys=False).splitlines())
    text = text.replace("\nprofiles:\n", f"\nprofiles:\n{tiny}", 1)
    assert yaml.safe_load(text)["profile"] == "tiny"
    (root / "params.yaml").write_text(text)
    subprocess.run(["git", "init", "-q"], cwd=root, check=True)
    return root


def _dvc(root, *args):
    from flows.dvc_tasks import dvc_env

    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=root, env=dvc_env(), capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_demo_flow_runs_every_stage_and_dvc_is_clean_after(project):
    from prefect.testing.utilities import prefect_test_harness

    from flows.pipeline import demo

    with prefect_test_harness(server_startup_timeout=120):
        results = demo(project)

    ingest = json.loads((project / "data/metrics/t_joint/ingest.json").read_text())
    assert np.isclose(ingest["diameter_mm"], 68.352, atol=0.01)  # the built part's known diameter
    assert results["evaluate"]["n_scenes"] == 2
    # The demo capture: its floor plane is the bin floor, 0.5 m below the camera.
    assert abs(results["import"]["floor_plane_d"] - 0.5) < 0.003
    truth = json.loads((project / "data/captures/demo/truth.json").read_text())
    assert len(truth["poses"]) == 4
    assert results["register"]["n_ground_truth"] == 4
    assert (project / "data/results/demo/scene.rrd").stat().st_size > 0
    assert (project / "data/fpcc/t_joint/model.pt").is_file()

    status = _dvc(project, "status")
    assert status.returncode == 0 and "up to date" in status.stdout, status.stdout + status.stderr

    (project / "data/results/demo/poses.json").unlink()
    rerun = _dvc(project, "repro")
    assert rerun.returncode == 0, rerun.stderr
    assert (project / "data/results/demo/poses.json").is_file()
    assert "Running stage 'train@t_joint'" not in rerun.stdout  # only the missing output's stage ran


@pytest.mark.slow
def test_watcher_trains_a_new_part_and_skips_unchanged_ones(project):
    """A mesh dropped into data/parts/ is registered and gets a trained, evaluated model; the
    parts already up to date are skipped; a second pass has nothing to do."""
    import trimesh
    from prefect.testing.utilities import prefect_test_harness

    from flows.watcher import watch_parts

    box = trimesh.creation.box(extents=[40.0, 24.0, 12.0])  # millimetres, as CAD exports are
    box.export(project / "data" / "parts" / "Bracket Block.stl")
    with prefect_test_harness(server_startup_timeout=120):
        first = watch_parts(project)
        second = watch_parts(project)
    assert first == {"added": ["bracket_block"], "trained": ["bracket_block"]}
    assert second == {"added": [], "trained": []}
    params = yaml.safe_load((project / "params.yaml").read_text())
    assert params["parts"]["bracket_block"]["mesh"] == "data/parts/Bracket Block.stl"
    assert "# binpick settings" in (project / "params.yaml").read_text()  # comments kept
    ingest = json.loads((project / "data/metrics/bracket_block/ingest.json").read_text())
    assert np.isclose(ingest["diameter_mm"], np.sqrt(40**2 + 24**2 + 12**2), rtol=1e-3)  # unit guessed: mm
    assert (project / "data/fpcc/bracket_block/model.pt").is_file()
    assert (project / "data/metrics/bracket_block/evaluate.json").is_file()


def test_models_are_registered_and_the_accepted_alias_points_at_the_checkpoint(project):
    """After the runs above: every training registered a version of fpcc-<part>, and evaluation
    (thresholds 0 in the tiny profile) pointed the alias at the version of the current model.pt."""
    import mlflow

    from stages.common import file_sha256

    mlflow.set_tracking_uri(f"sqlite:///{project / 'data' / 'mlflow' / 'mlflow.db'}")
    client = mlflow.MlflowClient()
    for part in ("t_joint", "bracket_block"):
        assert json.loads((project / f"data/metrics/{part}/evaluate.json").read_text())["accepted"] == 1.0
        accepted = client.get_model_version_by_alias(f"fpcc-{part}", "accepted")
        assert accepted.tags["checkpoint_sha256"] == file_sha256(project / f"data/fpcc/{part}/model.pt")
        assert accepted.tags["dvc_stage"] == f"train@{part}"
