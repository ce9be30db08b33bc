"""`binpick learn`: labelled captures are reviewed before use; a network is fine-tuned on the
approved ones when enough are new, and served (file and MLflow alias) only when no worse."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import box_part_model

from binpick.errors import BinpickError
from binpick.io.labelled_capture import LabelledCapture, save_labelled_capture
from binpick.io.part_model import save_part_model
from binpick.io.scene import SyntheticScene, save_scene
from binpick.labels import IGNORE
from binpick.layout import Layout
from binpick.network.checkpoint import read_checkpoint
from binpick.network.train import train_fpcc
from flows.learn import approved_captures, finetune, heldout, no_worse, pending_captures, review, served_checkpoint

from settings import PARAMS, changed

PART = "toy"
TRAIN = changed(
    PARAMS.train,
    width=8,
    embedding_dim=4,
    k_neighbours=8,
    n_points=200,
    batch_size=2,
    epochs=2,
    loss_anchors=64,
    patience_epochs=10,
)


def _patches(rng, k):
    """k flat 3 cm squares 5 cm apart, 100 points each: points (100 k, 3), labels (100 k,)."""
    pts = np.concatenate(
        [rng.uniform([0.05 * i, 0, 0.5], [0.05 * i + 0.03, 0.03, 0.5], (100, 3)) for i in range(k)]
    ).astype(np.float32)
    return pts, np.repeat(np.arange(k), 100).astype(np.int16)


def _scene(rng) -> SyntheticScene:
    pts, labels = _patches(rng, int(rng.integers(2, 5)))
    return SyntheticScene(
        np.zeros((1, 1, 3), np.float32),
        np.full((1, 1), -1, np.int16),
        np.eye(3),
        np.zeros((0, 4, 4)),
        np.zeros(0),
        np.eye(4),
        pts,
        np.tile(np.array([0, 0, -1], np.float32), (len(pts), 1)),
        labels,
    )


def _capture(rng) -> LabelledCapture:
    """Three patches, the last one unexplained (ignored)."""
    pts, labels = _patches(rng, 3)
    labels[labels == 2] = IGNORE
    return LabelledCapture(
        pts,
        np.tile(np.array([0, 0, -1], np.float32), (len(pts), 1)),
        labels,
        np.tile(np.eye(4), (2, 1, 1)),
        np.array([0.8, 0.7]),
        np.asarray(0.002),
    )


@pytest.fixture
def project(tmp_path):
    """A project folder with a toy part's synthetic scenes, a trained network and four labelled
    captures, two of which the hash holds back."""
    rng = np.random.default_rng(0)
    for split, n in (("train", 4), ("val", 2), ("test", 2)):
        (tmp_path / "data" / "scenes" / PART / split).mkdir(parents=True)
        for i in range(n):
            save_scene(tmp_path / "data" / "scenes" / PART / split / f"scene_{i:06d}.npz", _scene(rng), png=False)
    from binpick.network.train import load_views

    scenes = tmp_path / "data" / "scenes" / PART
    train_fpcc(
        load_views(scenes / "train"),
        load_views(scenes / "val"),
        TRAIN,
        0.02,
        1,
        tmp_path / "work",
        PART,
        0.06,
        progress=False,
    )
    (tmp_path / "data" / "fpcc" / PART).mkdir(parents=True)
    (tmp_path / "work" / "best.pt").replace(tmp_path / "data" / "fpcc" / PART / "model.pt")
    (tmp_path / "data" / "models" / PART).mkdir(parents=True)
    save_part_model(tmp_path / "data" / "models" / PART / "part.npz", box_part_model([0.03, 0.03, 0.002]))
    folder = Layout(tmp_path).real(PART)
    folder.mkdir(parents=True)
    names = [n for n in (f"c{i}" for i in range(40)) if heldout(n, 0.5)][:2] + [
        n for n in (f"c{i}" for i in range(40)) if not heldout(n, 0.5)
    ][:2]
    for name in names:
        save_labelled_capture(folder / f"{name}.npz", _capture(rng))
    return tmp_path


def _settings(tmp_path, **learn):
    return PARAMS.model_copy(
        update={
            "train": TRAIN,
            "segment": changed(PARAMS.segment, n_points=200, min_points=10),
            "learn": changed(
                PARAMS.learn, **{"min_new_scenes": 4, "finetune_epochs": 1, "heldout_share": 0.5, **learn}
            ),
            "tracking": changed(PARAMS.tracking, mlflow_uri=f"sqlite:///{tmp_path / 'mlflow' / 'mlflow.db'}"),
        }
    )


def test_captures_are_learnt_from_only_once_approved_as_they_are(project):
    folder = Layout(project).real(PART)
    shown = review(project, PART)
    assert shown.recording is not None and shown.recording.stat().st_size > 0 and len(shown.pending) == 4
    with pytest.raises(BinpickError, match="no pending labelled capture"):
        review(project, PART, approve=True, reject=["nope"])
    result = review(project, PART, approve=True, reject=[shown.pending[0]])
    assert sorted(result.approved + result.rejected) == sorted(shown.pending) and result.rejected == [shown.pending[0]]
    assert [p.stem for p in approved_captures(folder)] == sorted(shown.pending[1:]) and not pending_captures(folder)
    # Labelled again (other content): reviewed again before it is used.
    again = folder / f"{shown.pending[1]}.npz"
    save_labelled_capture(again, _capture(np.random.default_rng(99)))
    assert [p.stem for p in pending_captures(folder)] == [again.stem] and again.stem not in [
        p.stem for p in approved_captures(folder)
    ]
    assert json.loads((folder / "reviewed.json").read_text())[shown.pending[0]]["approved"] is False


def test_finetuning_waits_for_enough_new_captures_then_serves_a_network_no_worse(project):
    import mlflow

    review(project, PART, approve=True)
    base = project / "data" / "fpcc" / PART / "model.pt"
    waiting = finetune(project, _settings(project, min_new_scenes=5), PART, progress=False)
    assert waiting["finetuned"] is False and waiting["new"] == 4 and served_checkpoint(project, PART) == base

    # Any drop allowed: the fine-tuned network is served, registered and aliased.
    result = finetune(project, _settings(project, max_drop=1.0), PART, progress=False)
    assert result["finetuned"] and result["served"] and result["n_train_real"] == 2 and result["n_heldout_real"] == 2
    served = Layout(project).served_checkpoint(PART)
    assert served_checkpoint(project, PART) == served
    extra = read_checkpoint(served)["extra"]
    assert extra["finetuned_from"] == read_checkpoint(base)["sha256"]
    # It learnt from the two captures the hash does not hold back.
    assert extra["real_scenes"] == sorted(
        p.stem for p in Layout(project).real(PART).glob("*.npz") if not heldout(p.stem, 0.5)
    )
    mlflow.set_tracking_uri(f"sqlite:///{project / 'mlflow' / 'mlflow.db'}")
    version = mlflow.MlflowClient().get_model_version_by_alias(f"fpcc-{PART}", PARAMS.learn.serve_alias)
    assert str(version.version) == result["version"]
    # Nothing new since: the next scheduled run waits.
    assert finetune(project, _settings(project, min_new_scenes=1), PART, progress=False)["finetuned"] is False
    # A retrained model.pt supersedes the network fine-tuned from the one before it.
    state = read_checkpoint(base)
    state["metrics"] = {**state["metrics"], "retrained": 1.0}
    from binpick.network.checkpoint import write_state

    write_state(base, state)
    assert served_checkpoint(project, PART) == base


def test_a_network_worse_on_either_test_is_not_served():
    before = {"real_precision": 0.8, "real_recall": 0.7, "synthetic_precision": 0.95, "synthetic_recall": 0.9}
    assert no_worse(before, {**before, "real_recall": 0.9}, 0.0)
    assert not no_worse(before, {**before, "real_recall": 0.9, "synthetic_precision": 0.94}, 0.0)
    assert no_worse(before, {**before, "synthetic_precision": 0.94}, 0.02)
    assert not no_worse(before, {**before, "real_precision": 0.7}, 0.02)


def test_the_watcher_is_a_flow_that_fine_tunes_in_a_task_of_its_own():
    """`binpick serve` deploys watch_parts as a Prefect flow; the fine-tuning runs as its task (a
    decorator once slid onto the wrong function and the schedule silently stopped working)."""
    from prefect import Flow
    from prefect.tasks import Task

    from flows.watcher import finetune_part, watch_parts

    assert isinstance(watch_parts, Flow) and watch_parts.name == "watch-parts"
    assert isinstance(finetune_part, Task) and finetune_part.name == "finetune-part"
