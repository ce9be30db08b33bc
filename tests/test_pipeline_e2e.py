"""The whole pipeline through the Prefect demo flow driving DVC, on a copy of the project with a
tiny profile: every stage runs for real, `dvc status` is clean afterwards, a deleted output is
restored by `dvc repro`."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT, copy_project

TINY = {
    "ingest": {"n_surface_points": 8000},
    "camera": {"downscale": 8},
    "generate": {"n_train": 6, "n_val": 2, "n_test": 2, "placement": {"n_objects_min": 2, "n_objects_max": 4}},
    "train": {
        "n_points": 512,
        "width": 8,
        "embedding_dim": 8,
        "k_neighbours": 8,
        "epochs": 2,
        "batch_size": 2,
        "loss_anchors": 128,
    },
    "evaluate": {"accept_precision": 0.0, "accept_recall": 0.0},  # every model is accepted
    "import_capture": {},
    "segment": {"n_points": 512},
    "register": {},
    "render_demo": {"n_objects": 4, "downscale": 4},
}


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    # Edit the text, so that the copy keeps params.yaml's comments.
    text = (ROOT / "params.yaml").read_text().replace("\nprofile: quick\n", "\nprofile: tiny\n", 1)
    tiny = "".join(f"  {line}\n" for line in yaml.safe_dump({"tiny": TINY}, sort_keys=False).splitlines())
    text = text.replace("\nprofiles:\n", f"\nprofiles:\n{tiny}", 1)
    assert yaml.safe_load(text)["profile"] == "tiny"
    return copy_project(tmp_path_factory.mktemp("project"), text)


def _dvc(root, *args):
    from flows.dvc_tasks import dvc_env

    return subprocess.run(
        [sys.executable, "-m", "dvc", *args], cwd=root, env=dvc_env(), capture_output=True, text=True, timeout=600
    )


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
    # The recording holds what a reviewer looks for, under entity paths that mirror the frames.
    printed = subprocess.run(
        [str(Path(sys.executable).parent / "rerun"), "rrd", "print", str(project / "data/results/demo/scene.rrd")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert printed.returncode == 0, printed.stderr
    for entity in (
        "/camera/scene ",
        "/camera/segments ",
        "/camera/floor_plane ",
        "/camera/parts/0/mesh ",
        "/camera/truth/0 ",
        "/timings ",
    ):
        assert entity in printed.stdout, entity
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
    # A broken file sorted before it blocks nothing: it is set aside, the others are trained.
    (project / "data" / "parts" / "Angle.stl").write_bytes(b"solid nothing\nendsolid\n")
    with prefect_test_harness(server_startup_timeout=120):
        first = watch_parts(project)
        second = watch_parts(project)
    assert (first.added, first.ran) == (["angle", "bracket_block"], ["bracket_block"])
    assert list(first.failed) == ["angle"] and "Angle.stl" in first.failed["angle"]
    assert (second.added, second.ran, second.failed) == ([], [], {})
    assert list(second.set_aside) == ["angle"]  # not retried until its file changes
    assert first.notes == {"bracket_block": "unit guessed: mm"}
    params = yaml.safe_load((project / "params.yaml").read_text())
    assert params["parts"]["bracket_block"]["mesh"] == "data/parts/Bracket Block.stl"
    assert "# binpick settings" in (project / "params.yaml").read_text()  # comments kept
    ingest = json.loads((project / "data/metrics/bracket_block/ingest.json").read_text())
    assert np.isclose(ingest["diameter_mm"], np.sqrt(40**2 + 24**2 + 12**2), rtol=1e-3)  # unit guessed: mm
    assert (project / "data/fpcc/bracket_block/model.pt").is_file()
    assert (project / "data/metrics/bracket_block/evaluate.json").is_file()


@pytest.mark.slow
def test_models_are_registered_and_the_accepted_alias_points_at_the_checkpoint(project):
    """After the runs above: every training registered a version of fpcc-<part>, and evaluation
    (thresholds 0 in the tiny profile) pointed the alias at the version of the current model.pt."""
    import mlflow

    from binpick.io.digest import file_sha256

    mlflow.set_tracking_uri(f"sqlite:///{project / 'data' / 'mlflow' / 'mlflow.db'}")
    client = mlflow.MlflowClient()
    for part in ("t_joint", "bracket_block"):
        assert json.loads((project / f"data/metrics/{part}/evaluate.json").read_text())["accepted"] == 1.0
        accepted = client.get_model_version_by_alias(f"fpcc-{part}", "accepted")
        assert accepted.tags["checkpoint_sha256"] == file_sha256(project / f"data/fpcc/{part}/model.pt")
        assert accepted.tags["dvc_stage"] == f"train@{part}"


@pytest.mark.slow
def test_scene_flow_processes_a_folder_of_captures(project):
    """Two captures dropped in a folder are listed in params.yaml and each imported, segmented and
    registered; a second pass over the folder adds nothing and changes nothing."""
    from prefect.testing.utilities import prefect_test_harness

    from flows.pipeline import process_folder

    folder = project / "data" / "captures" / "monday"
    folder.mkdir(parents=True)
    for name in ("bin A.ply", "bin_b.ply"):
        shutil.copy(project / "data/captures/demo/capture.ply", folder / name)
    (folder / "notes.md").write_text("not a capture")
    with prefect_test_harness(server_startup_timeout=120):
        outcome, first = process_folder(project, folder, "t_joint")
        _, second = process_folder(project, folder, "t_joint")
    assert sorted(first) == ["bin_a", "bin_b"] and outcome.added == ["bin_a", "bin_b"] and not outcome.failed
    demo = json.loads((project / "data/metrics/scenes/demo/register.json").read_text())
    for name in first:  # the demo capture's frame: about the demo's parts are found
        assert demo["n_found"] / 2 <= first[name]["n_found"] <= demo["n_found"] + 2
        assert (project / f"data/results/{name}/poses.json").is_file()
    assert second == first
    captures = yaml.safe_load((project / "params.yaml").read_text())["captures"]
    # Written as the README says, without the optional keys (truth, intrinsics), and DVC ran it.
    assert captures["bin_a"] == {"file": "data/captures/monday/bin A.ply", "part": "t_joint", "unit": "mm"}


def _train_runs(project, part):
    import mlflow

    mlflow.set_tracking_uri(f"sqlite:///{project / 'data' / 'mlflow' / 'mlflow.db'}")
    experiment = mlflow.get_experiment_by_name(f"part-{part}")
    if experiment is None:
        return []
    runs = mlflow.search_runs([experiment.experiment_id], output_format="list")
    return [r for r in runs if r.info.run_name == f"train-{part}"]


def _completed_flow_runs(api_url):
    import urllib.request

    body = json.dumps({"flow_runs": {"state": {"type": {"any_": ["COMPLETED"]}}}, "limit": 200}).encode()
    request = urllib.request.Request(
        f"{api_url}/flow_runs/filter", data=body, headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return json.loads(response.read())
    except (TimeoutError, OSError):
        # On two cores the server shares them with the training it scheduled and can be slow to
        # answer; a late answer is asked again on the next poll, within the test's deadline.
        return []


@pytest.mark.slow
@pytest.mark.timeout(1200)  # the test's own deadline for the scheduled run is 900 s
def test_served_schedule_fires_and_trains_a_new_part_only(project):
    """`binpick serve` on a 5 s interval, against the local Prefect server it starts: a scheduled
    run picks up a newly dropped mesh and trains it; the parts already trained are not retrained;
    the new part's MLflow runs name the Prefect flow run that made them."""
    import os
    import signal
    import time

    import trimesh

    before = {part: len(_train_runs(project, part)) for part in ("t_joint", "bracket_block")}
    assert all(before.values())
    trimesh.creation.cylinder(radius=9.0, height=30.0, sections=48).export(project / "data" / "parts" / "spacer.stl")
    from flows.bench import free_port

    port = free_port()
    env = {**os.environ, "PREFECT_HOME": str(project / "data" / "prefect"), "TQDM_DISABLE": "1"}
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows.cli", "serve", "--interval-s", "5", "--port", str(port)],
        cwd=project,
        env=env,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    api_url = f"http://127.0.0.1:{port}/api"
    scheduled = []
    try:
        # About 2 minutes on an idle 2-core machine; one CI run took over 8 minutes.
        deadline = time.monotonic() + 900
        while time.monotonic() < deadline and proc.poll() is None:
            if (project / "data/metrics/spacer/evaluate.json").is_file():
                runs = _completed_flow_runs(api_url)
                scheduled = [r for r in runs if r["name"] == "watch-parts" and r["deployment_id"]]
                if scheduled:
                    break
            time.sleep(2)
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            output, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            output, _ = proc.communicate()
    reached = [
        p.relative_to(project).as_posix()
        for p in (
            project / "data/metrics/spacer/ingest.json",
            project / "data/scenes/spacer",
            project / "data/fpcc/spacer/model.pt",
            project / "data/metrics/spacer/evaluate.json",
        )
        if p.exists()
    ]
    # Serve's own log lines (not the tracebacks an interrupt prints) say where the runs were.
    said = "\n".join(line for line in output.splitlines() if line[:1].isdigit())[-3000:]
    assert scheduled, f"no scheduled watcher run completed; the spacer had {reached}; serve said:\n{said}"
    assert (project / "data/fpcc/spacer/model.pt").is_file()
    assert {part: len(_train_runs(project, part)) for part in before} == before  # up to date: skipped
    (spacer_run,) = _train_runs(project, "spacer")
    assert spacer_run.data.tags["prefect.flow_run_name"] == "train-spacer"
    assert spacer_run.data.tags["dvc_stage"] == "train@spacer"
    assert "samples/samples.rrd" in {
        a.path for a in __import__("mlflow").MlflowClient().list_artifacts(spacer_run.info.run_id, "samples")
    }


def _quality_metrics(project, part):
    """A part's DVC metrics without the timings, which no rerun reproduces."""
    out = {}
    for path in sorted((project / "data" / "metrics" / part).glob("*.json")):
        out[path.stem] = {k: v for k, v in json.loads(path.read_text()).items() if not k.endswith("_s")}
    return out


@pytest.mark.slow
def test_one_parts_params_rerun_only_its_stages_and_a_rerun_reproduces_it(project):
    """Changing bracket_block's params re-runs only bracket_block's stages; changing them back and
    running again without DVC's run cache gives the same data set, weights and metrics."""
    from ruamel.yaml import YAML

    from binpick.io.digest import file_sha256

    def lock_hash(stage, out):
        lock = yaml.safe_load((project / "dvc.lock").read_text())["stages"][stage]
        return next(o["md5"] for o in lock["outs"] if o["path"] == out)

    before = (
        _quality_metrics(project, "bracket_block"),
        file_sha256(project / "data/fpcc/bracket_block/model.pt"),
        lock_hash("generate@bracket_block", "data/scenes/bracket_block"),
    )
    yaml_rt = YAML()
    original = (project / "params.yaml").read_text()
    doc = yaml_rt.load(original)
    doc["parts"]["bracket_block"]["train"] = {"epochs": 1}
    with open(project / "params.yaml", "w") as fh:
        yaml_rt.dump(doc, fh)
    changed = _dvc(project, "repro")
    assert changed.returncode == 0, changed.stderr
    ran = {line.split("'")[1] for line in changed.stdout.splitlines() if line.startswith("Running stage")}
    assert "train@bracket_block" in ran and all(s.endswith("@bracket_block") for s in ran), ran

    (project / "params.yaml").write_text(original)
    again = _dvc(project, "repro", "--no-run-cache")
    assert again.returncode == 0, again.stderr
    assert "Running stage 'train@bracket_block'" in again.stdout
    after = (
        _quality_metrics(project, "bracket_block"),
        file_sha256(project / "data/fpcc/bracket_block/model.pt"),
        lock_hash("generate@bracket_block", "data/scenes/bracket_block"),
    )
    assert after == before
    assert "up to date" in _dvc(project, "status").stdout
