"""`binpick service`: a resident process answering "picks for this capture" for a robot cell.

It loads every part of the project once (part model, PPF model, network, grasps, verification
thresholds), serving a part's network only when the evaluate stage accepted it (GET /health says
why a part is not served), and answers over HTTP/JSON and over a plain TCP line protocol (one JSON
request per line, one JSON answer per line), on 127.0.0.1 by default. Requests and answers are the
pydantic types of flows/service_api.py, published as the OpenAPI schema at /openapi.json (/docs).
The answer is the picks.json document of the batch pipeline (binpick.io.picks), plus the
request's id, its timings per step and the poses. The scene path is the library's
(binpick.scene.process.process), the one the DVC stages and the benchmarks call, seeded by the
capture's content as they are.

Requests are answered one at a time, on one thread (two parts' models never fight over the
cores); up to service.max_queue more wait, further ones are refused as busy. A bad request gets an
error answer and the service goes on. POST /reload (or {"reload": true}) loads the parts again: a
part trained after the service started is served from the next request on, without a restart and
without dropping a request in progress. Each answered request is kept for review in
<keep_dir>/requests/<date>/<id>/ (the capture, request.json, poses.json, picks.json and a rerun
recording) and logged to MLflow (experiment `service`), both after the answer is sent; the newest
service.keep_requests are kept.

HTTP:
  GET  /health                      {"status": "ok", "parts": [...], "not_served": {...}, "answered": n, ...}
  POST /reload                      the same, after loading the parts again
  POST /picks?part=P&format=zdf&unit=mm   the capture file as the body (application/octet-stream)
  POST /picks  {"part": P, "path": FILE, "unit": "mm"}   a capture file on this machine
  POST /picks  {"part": P, "camera": true}               a frame from the connected Zivid camera
TCP: the same JSON objects, one per line ({"health": true}, {"reload": true}; an upload as
  "data_b64" with "format"), each with "token" when one is required (HTTP: Authorization: Bearer);
  or, for a robot controller without JSON, `PICK <part> [ur|abb|kuka|fanuc] [<path>]` answered by
  one line of numbers (flows/service_lines.py; clients/ur/binpick_pick.script).
  GET  /                          the operator page (flows/operator.py); /operator/state its figures
Errors: {"error": "..."} (HTTP 400 bad request, 401 token, 404 unknown part, 409 reload refused,
  413 too large, 429 rate, 503 busy).

This module holds the service's state and its answering (PickService); flows/service_http.py the
HTTP application and `run_service`, flows/service_lines.py the line protocol, flows/service_api.py
the request and answer types, flows/service_keeper.py the keeping of requests.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import shutil
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from binpick.cell.retries import FailedGrips
from binpick.errors import BinpickError
from binpick.io.capture import CAPTURE_SUFFIXES, ImportOptions, load_capture
from binpick.io.digest import file_sha256
from binpick.io.picks import picks_document, pose_entries
from binpick.layout import Layout
from binpick.params import Params, ServiceParams, load_params
from binpick.scene.mixed import process_mixed
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds
from flows.learn import served_checkpoint
from flows.operator import OperatorLog
from flows.service_api import PicksRequest, validation_message
from flows.service_keeper import Keeper, list_requests

log = logging.getLogger("binpick.service")

LOOPBACK = ("127.0.0.1", "localhost", "::1")

# A kept request's id (`<UTC stamp>-<part>`) and the files of it the operator page links to.
KEPT_ID = re.compile(r"\d{8}T\d{12}-[A-Za-z0-9_.-]+")
VIEWABLE = {"overlay.png": "image/png", "scene.rrd": "application/octet-stream", "picks.json": "application/json"}


class RequestError(Exception):
    """A request the service refuses: an HTTP status and one line."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Served:
    models: PartModels
    params: Params
    T_base_from_cam: np.ndarray | None


def load_parts(root: Path, params_path: Path) -> tuple[dict[str, Served], dict[str, str]]:
    """Every part of the project whose models are built (data/models/<part>/ part.npz, ppf.npz,
    grasps.json; its network when trained) and whose network the evaluate stage accepted; and
    the parts not served, with the reason."""
    base = load_params(params_path)
    layout = Layout(root)
    served: dict[str, Served] = {}
    not_served: dict[str, str] = {}
    for name in base.parts:
        needed = [layout.part_model(name), layout.ppf_model(name), layout.grasps(name)]
        if not all(p.is_file() for p in needed):
            not_served[name] = "its models are not built (run make repro)"
            log.warning("not serving %s: %s", name, not_served[name])
            continue
        refused = _not_accepted(layout, name)
        if refused:
            not_served[name] = refused
            log.warning("not serving %s: %s", name, refused)
            continue
        p = load_params(params_path, name)
        # The fine-tuned network when `binpick learn finetune` found it no worse (flows/learn.py).
        checkpoint = served_checkpoint(root, name)
        models = PartModels.load(p, needed[0], needed[1], checkpoint, needed[2], layout.verification(name))
        served[name] = Served(
            models, p, np.asarray(p.pick.T_base_from_cam) if p.pick.T_base_from_cam is not None else None
        )
        log.info(
            "serving %s (%s, %d %s grasps)",
            name,
            f"segmentation ({checkpoint.name}) + registration"
            if models.segmenter and checkpoint
            else "registration only",
            len(models.grasps or []),
            p.pick.gripper,
        )
    if not served:
        why = "; ".join(f"{n}: {r}" for n, r in not_served.items())
        raise BinpickError(f"no part of {params_path} can be served ({why or 'no parts'}): run `make repro` first")
    return served, not_served


def _not_accepted(layout: Layout, part: str) -> str | None:
    """Why a part's trained network must not be served (the evaluate stage refused it, or judged
    another file: the SHA-256 it recorded is not the checkpoint's), None when it may be (accepted,
    or no network: registration only)."""
    checkpoint = layout.checkpoint(part)
    if not checkpoint.is_file():
        return None
    metrics = layout.part_metrics(part, "evaluate")
    if not metrics.is_file():
        return "its network has not been evaluated (run make repro)"
    figures = json.loads(metrics.read_text())
    judged = figures.get("checkpoint_sha256")
    if judged is None:
        log.warning(
            "%s: %s does not name the network it judged (written before evaluate recorded digests); "
            "serving it as accepted: run make repro to re-judge",
            part,
            metrics.name,
        )
    elif judged != file_sha256(checkpoint):
        return "its network has not been evaluated since it was trained (run make repro)"
    if not figures.get("accepted"):
        return (
            "its network was not accepted by evaluate (segmentation precision "
            f"{figures.get('precision', float('nan')):.2f}, "
            f"recall {figures.get('recall', float('nan')):.2f} below evaluate.accept_precision / accept_recall)"
        )
    return None


class PickService:
    """The service's state: the loaded parts, the queue, the limits, the keeper of requests."""

    def __init__(self, root: Path, params_path: Path, keep_mlflow: bool = True):
        self.root = Path(root)
        self.params = load_params(params_path)
        self.settings: ServiceParams = self.params.service
        self.params_path = Path(params_path)
        self.parts, self.not_served = load_parts(self.root, params_path)
        self.token = os.environ.get(self.settings.token_env) or None
        self.started = time.monotonic()
        self.answered = 0
        # One request at a time, always on the same thread: numerics on ever new threads grow
        # the allocator's per-thread arenas and the thread pools of torch and Open3D.
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="binpick-answer")
        self._waiting = 0
        self._count = threading.Lock()
        self._recent: deque[float] = deque()
        self.operator = OperatorLog()
        self._keeper = Keeper(
            self.root / self.settings.keep_dir,
            self.settings.keep_requests,
            self.params.tracking.mlflow_uri if keep_mlflow else None,
            keep_mlflow,
        )

    # -- checks --------------------------------------------------------------------------------

    def check_token(self, given: str | None) -> None:
        if self.token is not None and given != self.token:
            raise RequestError(401, "missing or wrong token")

    def check_rate(self) -> None:
        now = time.monotonic()
        with self._count:
            while self._recent and now - self._recent[0] > 60.0:
                self._recent.popleft()
            if len(self._recent) >= self.settings.max_requests_per_min:
                raise RequestError(429, f"more than {self.settings.max_requests_per_min} requests in a minute")
            self._recent.append(now)

    @property
    def max_bytes(self) -> int:
        return int(self.settings.max_request_mb * 1024 * 1024)

    def health(self) -> dict[str, Any]:
        return {
            "status": "ok",
            "parts": sorted(self.parts),
            "not_served": self.not_served,
            "answered": self.answered,
            "waiting": self._waiting,
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def reload(self) -> dict[str, Any]:
        """Load the project's parts again (a part trained, fine-tuned or refused since) and serve
        them from the next request on; a request in progress finishes with the models it began
        with. Refused (the old parts kept) when no part could be loaded."""
        try:
            parts, not_served = load_parts(self.root, self.params_path)
        except BinpickError as exc:
            raise RequestError(409, f"reload refused, still serving {', '.join(sorted(self.parts))}: {exc}") from None
        self.parts, self.not_served = parts, not_served  # one assignment each: a request reads one or the other
        log.info("reloaded: serving %s", ", ".join(sorted(parts)))
        return self.health()

    # -- answering -----------------------------------------------------------------------------

    async def answer(self, request: PicksRequest, payload: bytes | None = None) -> dict[str, Any]:
        """The picks for one request (see the module's docstring); raises RequestError. Called
        on the event loop: the work goes straight to the one answering thread."""
        names = request.parts or [request.part or ""]
        unknown = [n for n in names if n not in self.parts]
        if unknown:
            raise RequestError(404, f"unknown part {unknown[0]!r} (serving: {', '.join(sorted(self.parts))})")
        served = [self.parts[n] for n in names]
        with self._count:
            if self._waiting >= self.settings.max_queue + 1:
                raise RequestError(503, f"busy: {self._waiting} requests in progress or waiting")
            self._waiting += 1
        try:
            return await asyncio.wrap_future(self._worker.submit(self._answer, names, served, request, payload))
        finally:
            with self._count:
                self._waiting -= 1

    def _capture_file(self, request: PicksRequest, payload: bytes | None, folder: Path) -> Path:
        """The capture as a file: the upload written into the request's folder, a named file, or a camera frame."""
        if payload is not None:
            fmt = (request.format or "").lower().lstrip(".")
            if f".{fmt}" not in CAPTURE_SUFFIXES:
                raise RequestError(
                    400,
                    "an uploaded capture needs its format: one of "
                    f"{', '.join(s.lstrip('.') for s in CAPTURE_SUFFIXES)}",
                )
            path = folder / f"capture.{fmt}"
            path.write_bytes(payload)
            return path
        if request.path:
            path = Path(request.path)
            path = path if path.is_absolute() else self.root / path
            allowed = [self.root, *(Path(f) for f in self.settings.capture_folders)]
            # The client's own words in an answer, never where the project lies on this machine.
            if not any(path.resolve().is_relative_to(a.resolve()) for a in allowed):
                raise RequestError(400, f"{request.path}: outside the project and service.capture_folders")
            if not path.is_file():
                raise RequestError(400, f"{request.path}: capture file not found")
            return path
        if request.camera:
            from binpick.cell.zivid_camera import grab_to_file

            path = folder / "capture.ply"
            try:
                grab_to_file(path, self.params.zivid_camera)
            except BinpickError as exc:
                raise RequestError(400, f"camera: {exc}") from None
            return path
        raise RequestError(400, 'a request names a capture: an upload (with its format), a "path" or "camera": true')

    def _for_client(self, message: str, path: Path, shown: str) -> str:
        """An error message with the capture named as the client named it (see public)."""
        for p in sorted({str(path), str(path.resolve())}, key=len, reverse=True):
            message = message.replace(p, shown)
        return self.public(message)

    def refused(self, exc: RequestError, part: str | None) -> str:
        """A refusal counted for the operator page; its message, as a client may read it."""
        message = self.public(str(exc))
        self.operator.refused(exc.status, message, part)
        return message

    def public(self, message: str) -> str:
        """A message for a client: any file of the project named relative to the project, never
        where the project lies on this machine."""
        for root in sorted({str(self.root), str(self.root.resolve())}, key=len, reverse=True):
            message = message.replace(root + os.sep, "").replace(root, ".")
        return message

    def _answer(
        self, names: list[str], served: list[Served], request: PicksRequest, payload: bytes | None
    ) -> dict[str, Any]:
        """One request answered: the parts as the project names them and their models (one part,
        or several: request.parts, binpick/scene/mixed.py)."""
        unit, first = request.unit, served[0]
        mixed = request.parts is not None
        t0 = time.perf_counter()
        stamp = datetime.now(UTC)
        request_id = f"{stamp:%Y%m%dT%H%M%S%f}-{'-'.join(names)}"
        folder = self._keeper.folder(request_id)
        try:
            path = self._capture_file(request, payload, folder)
            uploaded = f"the uploaded {path.suffix[1:]} capture"
            shown = request.path or ("the camera's frame" if request.camera else uploaded)
            t_read = time.perf_counter()
            try:
                frame = load_capture(path, ImportOptions(unit))
            except BinpickError as exc:
                raise RequestError(400, self._for_client(str(exc), path, shown)) from None
            # Seeds from the capture's content, as the DVC stages take them: the same capture
            # gets the same answer here and when `binpick requests --add` runs it through them.
            seeds = SceneSeeds.of_capture(first.params.seed, frame.xyz_m, frame.rgb)
            t1 = time.perf_counter()
            failed = FailedGrips.at(request.failed_grasps) if request.failed_grasps else None
            try:
                if mixed:
                    models = {name: s.models for name, s in zip(names, served, strict=True)}
                    pick = first.params.pick
                    priority = request.priority if request.priority is not None else pick.part_priority
                    quota = request.quota if request.quota is not None else pick.part_quota
                    result: Any = process_mixed(
                        frame.xyz_m, frame.rgb, frame.shape, models, seeds, priority, quota=quota, failed=failed
                    )
                else:
                    result = process(frame.xyz_m, frame.rgb, frame.shape, first.models, seeds, failed=failed)
            except BinpickError as exc:
                raise RequestError(400, self._for_client(f"{path}: {exc}", path, shown)) from None
        except RequestError:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        t2 = time.perf_counter()
        pose_format = request.pose_format or first.params.pick.pose_format
        if mixed:
            doc = result.document(
                request_id,
                {name: s.params.pick.gripper for name, s in zip(names, served, strict=True)},
                first.T_base_from_cam,
                pose_format,
            )
            posed = result.posed()
        else:
            assert result.picks is not None
            doc = picks_document(
                request_id,
                names[0],
                first.params.pick.gripper,
                result.picks,
                first.T_base_from_cam,
                pose_format,
            )
            posed = [(None, p) for p in result.poses]
        timings = {"read_s": t1 - t_read, **result.timings_s, "pipeline_s": t2 - t1, "total_s": t2 - t0}
        doc["request_id"] = request_id
        doc["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
        doc["poses"] = pose_entries(posed)
        self.answered += 1
        self.operator.answered(doc)
        self._keeper.keep(folder, path, doc, None if mixed else result, first, unit, frame)
        return doc

    def kept_files(self) -> dict[str, list[str]]:
        """The kept requests, newest first: request id -> the names of its files."""
        return {p.name: sorted(f.name for f in p.iterdir()) for p in list_requests(self._keeper.requests)}

    def kept_file(self, request_id: str, name: str) -> Path:
        """A file of a kept request a browser may fetch (not request.json: it names this machine's paths)."""
        if name not in VIEWABLE or not KEPT_ID.fullmatch(request_id):
            raise RequestError(404, "no such file")
        path = self._keeper.path_of(request_id) / name
        if not path.is_file():
            raise RequestError(404, f"{request_id}/{name} is not kept (service.keep_requests keeps the newest)")
        return path

    def close(self) -> None:
        self._worker.shutdown(wait=True)
        self._keeper.close()


def json_object(text: bytes) -> dict[str, Any]:
    try:
        fields = json.loads(text)
    except ValueError as exc:
        raise RequestError(400, f"not JSON: {exc}") from None
    if not isinstance(fields, dict):
        raise RequestError(400, "the request must be a JSON object")
    return fields


def picks_request(fields: dict[str, Any]) -> PicksRequest:
    try:
        return PicksRequest.model_validate(fields)
    except ValidationError as exc:
        raise RequestError(400, validation_message(exc)) from None
