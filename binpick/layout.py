"""Where the pipeline keeps its files under a project's `data/` folder: the one owner of that
layout. dvc.yaml spells the same paths for DVC (tests/test_layout.py renders its outs and checks
they are these); everything in Python asks a `Layout`.

Per part `<p>`:  data/models/<p>/{part.npz, ppf.npz, grasps.json}, data/scenes/<p>/,
data/fpcc/<p>/{model.pt, served.pt, verification.json}, data/work/<p>/, data/metrics/<p>/<stage>.json,
data/real/<p>/<capture>.npz (labelled captures).
Per capture `<c>`: data/results/<c>/{cloud.npz, segments.npz, poses.json, picks.json, *.rrd},
data/metrics/scenes/<c>/<stage>.json.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

DATA = Path("data")


@dataclass(frozen=True)
class Layout:
    """The `data/` paths of the project at `root` (absolute when root is)."""

    root: Path

    @property
    def data(self) -> Path:
        return Path(self.root) / DATA

    # -- project files
    @property
    def parts_folder(self) -> Path:
        """Where new part meshes are dropped (the watcher's inbox)."""
        return self.data / "parts"

    @property
    def captures_folder(self) -> Path:
        return self.data / "captures"

    @property
    def service_captures(self) -> Path:
        """Where `binpick requests --add` copies a kept service request's capture."""
        return self.captures_folder / "service"

    @property
    def pipeline_vars(self) -> Path:
        return self.data / "pipeline.yaml"

    @property
    def set_aside(self) -> Path:
        return self.data / "set_aside.yaml"

    @property
    def hand_eye(self) -> Path:
        return self.data / "hand_eye.json"

    @property
    def mlflow(self) -> Path:
        return self.data / "mlflow"

    @property
    def mlflow_store(self) -> Path:
        """The local MLflow store when params name none (tracking.mlflow_uri: null)."""
        return self.mlflow / "mlflow.db"

    @property
    def prefect(self) -> Path:
        return self.data / "prefect"

    @property
    def models_folder(self) -> Path:
        """Every part's models (part_folder); a mixed capture's stage depends on all of it."""
        return self.data / "models"

    @property
    def networks_folder(self) -> Path:
        """Every part's network (network_folder); a mixed capture's stage depends on all of it."""
        return self.data / "fpcc"

    # -- per part
    def part_folder(self, part: str) -> Path:
        return self.models_folder / part

    def part_model(self, part: str) -> Path:
        return self.part_folder(part) / "part.npz"

    def ppf_model(self, part: str) -> Path:
        return self.part_folder(part) / "ppf.npz"

    def grasps(self, part: str) -> Path:
        return self.part_folder(part) / "grasps.json"

    def grasps_recording(self, part: str) -> Path:
        return self.part_folder(part) / "grasps.rrd"

    def distractors(self, part: str) -> Path:
        """The other parts the part's training scenes mix in (binpick check writes it)."""
        return self.data / "distractors" / f"{part}.json"

    def scenes(self, part: str) -> Path:
        """The part's generated data set (train/, val/, test/)."""
        return self.data / "scenes" / part

    def network_folder(self, part: str) -> Path:
        return self.networks_folder / part

    def checkpoint(self, part: str) -> Path:
        """The network the train stage wrote (what the batch stages use)."""
        return self.network_folder(part) / "model.pt"

    def served_checkpoint(self, part: str) -> Path:
        """A fine-tuned network the service serves while it descends from checkpoint()."""
        return self.network_folder(part) / "served.pt"

    def verification(self, part: str) -> Path:
        """The pose verification thresholds the verify stage chose for checkpoint()."""
        return self.verification_of(self.checkpoint(part))

    @staticmethod
    def verification_of(checkpoint: Path) -> Path:
        """The verification thresholds chosen for the network at `checkpoint` (beside it)."""
        return checkpoint.with_name("verification.json")

    def work(self, part: str) -> Path:
        """Scratch of a part's training and fine-tuning (resume points, recordings)."""
        return self.data / "work" / part

    def part_metrics(self, part: str, stage: str) -> Path:
        return self.data / "metrics" / part / f"{stage}.json"

    def real(self, part: str) -> Path:
        """The part's labelled captures (learning from the cell)."""
        return self.data / "real" / part

    def labelled_capture(self, part: str, capture: str) -> Path:
        return self.real(part) / f"{capture}.npz"

    # -- per capture
    def results(self, capture: str) -> Path:
        return self.data / "results" / capture

    def cloud(self, capture: str) -> Path:
        return self.results(capture) / "cloud.npz"

    def segments(self, capture: str) -> Path:
        return self.results(capture) / "segments.npz"

    def poses(self, capture: str) -> Path:
        return self.results(capture) / "poses.json"

    def picks(self, capture: str) -> Path:
        return self.results(capture) / "picks.json"

    def scene_recording(self, capture: str) -> Path:
        return self.results(capture) / "scene.rrd"

    def picks_recording(self, capture: str) -> Path:
        return self.results(capture) / "picks.rrd"

    def bin_recording(self, capture: str) -> Path:
        return self.results(capture) / "bin.rrd"

    def overlay(self, capture: str) -> Path:
        return self.results(capture) / "overlay.png"

    # -- the running cell
    @property
    def cell_runs(self) -> Path:
        """`binpick cell run`'s cycles, one folder per run."""
        return self.data / "cell" / "runs"

    @property
    def cell_stop(self) -> Path:
        """A file here asks a running `binpick cell run` to stop after its cycle."""
        return self.data / "cell" / "STOP"

    def scene_metrics(self, capture: str, stage: str) -> Path:
        return self.data / "metrics" / "scenes" / capture / f"{stage}.json"
