"""The pick service's keeper: every answered request kept for review, off the answering path
(a thread of its own), and the newest service.keep_requests kept: the capture, request.json,
poses.json, picks.json and a rerun recording (scene.rrd) in <keep_dir>/requests/<date>/<id>/,
and an MLflow run in experiment `service`."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import shutil
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from binpick.io.atomic import atomic_path
from binpick.io.picks import write_picks_document
from binpick.io.poses import save_poses
from review.pick_recording import write_pick_recording

if TYPE_CHECKING:
    from flows.service import Served

log = logging.getLogger("binpick.service")


class Keeper:
    """Keeps answered requests for review, off the answering path (a thread of its own): the
    capture, request.json, poses.json, picks.json and scene.rrd in a dated folder, an MLflow
    run, and the retention limit."""

    def __init__(self, keep_dir: Path, limit: int, mlflow_uri: str | None, log_mlflow: bool):
        self.requests = keep_dir / "requests"
        self.limit = limit
        self.mlflow_uri = mlflow_uri
        self.log_mlflow = log_mlflow
        self._jobs: queue.Queue[tuple | None] = queue.Queue()
        self._stream: Any = None  # one rerun stream for every recording (a stream per file leaks threads)
        self._thread = threading.Thread(target=self._run, name="binpick-keeper", daemon=True)
        self._thread.start()

    def folder(self, request_id: str) -> Path:
        """A new request's folder, made."""
        path = self.path_of(request_id)
        path.mkdir(parents=True, exist_ok=True)
        return path

    def path_of(self, request_id: str) -> Path:
        """Where a request is kept: <requests>/<its UTC day>/<id> (the id begins with its stamp, YYYYMMDDT...)."""
        return self.requests / f"{request_id[:4]}-{request_id[4:6]}-{request_id[6:8]}" / request_id

    def keep(self, folder: Path, capture: Path, doc: dict, result, served: Served, unit: str, frame) -> None:
        """Keep one answered request (frame: the capture as loaded, binpick.io.capture; result:
        the scene path's, None for a mixed bin, whose poses, recording and image are not kept)."""
        self._jobs.put((folder, capture, doc, result, served, unit, frame))

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join(timeout=60)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                self._keep(*job)
            except Exception:  # noqa: BLE001 - a review copy that failed must not stop the service
                log.exception("keeping request %s for review failed", job[2].get("request_id"))
            finally:
                self._jobs.task_done()

    def _keep(self, folder: Path, capture: Path, doc: dict, result, served: Served, unit: str, frame) -> None:
        if capture.parent != folder:  # a named file: keep a copy (a link where the disk allows)
            target = folder / f"capture{capture.suffix}"
            try:
                os.link(capture, target)
            except OSError:
                shutil.copyfile(capture, target)
        part = served.models.part
        write_picks_document(
            folder / "picks.json", {k: v for k, v in doc.items() if k not in ("timings_s", "poses", "request_id")}
        )
        names = doc.get("parts") or [part.name]
        self._write_request(folder, doc, capture, unit)
        if result is not None:  # one part: its poses, the image and the recording (not for a mixed bin)
            save_poses(folder / "poses.json", part.name, result.poses)
            if frame.shape is not None:  # an image to draw on: the operator page shows it
                write_overlay(folder / OVERLAY, frame, part, result)
            if self._stream is None:
                import rerun as rr

                self._stream = rr.RecordingStream("binpick", recording_id="binpick-service")
            write_pick_recording(
                folder / "scene.rrd",
                doc["request_id"],
                result.cloud,
                part,
                result.poses,
                result.picks,
                served.params.pick.gripper,
                served.params.pick,
                self._stream,
            )
        scores = [p["score"] for p in doc.get("poses", [])]
        self._log(doc, names, float(np.mean(scores)) if scores else 0.0)
        self._prune()

    def _write_request(self, folder: Path, doc: dict, capture: Path, unit: str) -> None:
        record = {
            "request_id": doc["request_id"],
            **({"parts": doc["parts"]} if "parts" in doc else {"part": doc["part"]}),
            "timings_s": doc["timings_s"],
            "counts": doc["counts"],
            "source": str(capture),
            "unit": unit,
        }
        (folder / "request.json").write_text(json.dumps(record, indent=1) + "\n")

    def _log(self, doc: dict, names: list[str], score_mean: float) -> None:
        if not self.log_mlflow:
            return
        from review.tracking import mlflow_run

        tags = {"part": ",".join(names), "request_id": doc["request_id"]}
        with mlflow_run("service", doc["request_id"], self.mlflow_uri, tags):
            import mlflow

            mlflow.log_metrics({**doc["timings_s"], **doc["counts"], "score_mean": score_mean})

    def _prune(self) -> None:
        kept = list_requests(self.requests)
        for old in kept[self.limit :]:
            shutil.rmtree(old, ignore_errors=True)
            with contextlib.suppress(OSError):
                old.parent.rmdir()  # the day's folder, once empty


OVERLAY = "overlay.png"


def write_overlay(path: Path, frame, part, result) -> None:
    """The capture's image with the poses and the chosen pick drawn (binpick.scene.overlay)."""
    from PIL import Image

    from binpick.scene.overlay import pick_overlay

    first = result.picks.picks[0] if result.picks is not None and result.picks.picks else None
    image = pick_overlay(
        frame.xyz_m,
        frame.rgb,
        frame.shape,
        part.points_m.astype(np.float64),
        np.array([p.T_cam_from_model for p in result.poses]).reshape(-1, 4, 4),
        [p.score for p in result.poses],
        (first.T_cam_from_pregrasp, first.T_cam_from_grasp) if first is not None else None,
    )
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")


def list_requests(requests: Path) -> list[Path]:
    """Kept request folders, newest first."""
    if not requests.is_dir():
        return []
    return sorted(
        (p for day in requests.iterdir() if day.is_dir() for p in day.iterdir() if p.is_dir()),
        key=lambda p: p.name,
        reverse=True,
    )
