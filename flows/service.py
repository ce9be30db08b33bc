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
  one line of numbers (_text_answer; clients/ur/binpick_pick.script).
Errors: {"error": "..."} (HTTP 400 bad request, 401 token, 404 unknown part, 409 reload refused,
  413 too large, 429 rate, 503 busy).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import os
import re
import shutil
import threading
import time
import typing
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from binpick.errors import BinpickError
from binpick.io.capture import CAPTURE_SUFFIXES, ImportOptions, load_capture
from binpick.io.digest import file_sha256
from binpick.io.picks import VERSION as PICKS_VERSION
from binpick.io.picks import picks_document
from binpick.layout import Layout
from binpick.params import Params, ServiceParams, load_params
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds
from flows.learn import served_checkpoint
from flows.operator import OperatorLog, operator_state, render_page
from flows.service_api import ErrorAnswer, Health, PicksAnswer, PicksRequest, validation_message
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
        served = self.parts.get(request.part)
        if served is None:
            raise RequestError(404, f"unknown part {request.part!r} (serving: {', '.join(sorted(self.parts))})")
        with self._count:
            if self._waiting >= self.settings.max_queue + 1:
                raise RequestError(503, f"busy: {self._waiting} requests in progress or waiting")
            self._waiting += 1
        try:
            return await asyncio.wrap_future(self._worker.submit(self._answer, served, request, payload))
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

    def public(self, message: str) -> str:
        """A message for a client: any file of the project named relative to the project, never
        where the project lies on this machine."""
        for root in sorted({str(self.root), str(self.root.resolve())}, key=len, reverse=True):
            message = message.replace(root + os.sep, "").replace(root, ".")
        return message

    def _answer(self, served: Served, request: PicksRequest, payload: bytes | None) -> dict[str, Any]:
        part, unit = request.part, request.unit
        t0 = time.perf_counter()
        stamp = datetime.now(UTC)
        request_id = f"{stamp:%Y%m%dT%H%M%S%f}-{part}"
        folder = self._keeper.folder(stamp, request_id)
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
            seeds = SceneSeeds.of_capture(served.params.seed, frame.xyz_m, frame.rgb)
            t1 = time.perf_counter()
            try:
                result = process(frame.xyz_m, frame.rgb, frame.shape, served.models, seeds)
            except BinpickError as exc:
                raise RequestError(400, self._for_client(f"{path}: {exc}", path, shown)) from None
        except RequestError:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        t2 = time.perf_counter()
        assert result.picks is not None
        doc = picks_document(
            request_id,
            part,
            served.params.pick.gripper,
            result.picks,
            served.T_base_from_cam,
            request.pose_format or served.params.pick.pose_format,
        )
        timings = {"read_s": t1 - t_read, **result.timings_s, "pipeline_s": t2 - t1, "total_s": t2 - t0}
        doc["request_id"] = request_id
        doc["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
        doc["poses"] = [
            {"T_cam_from_model": np.asarray(p.T_cam_from_model).round(9).tolist(), "score": round(p.score, 6)}
            for p in result.poses
        ]
        self.answered += 1
        self.operator.answered(doc)
        self._keeper.keep(folder, path, doc, result, served, unit, frame)
        return doc

    def kept_files(self) -> dict[str, list[str]]:
        """The kept requests, newest first: request id -> the names of its files."""
        return {p.name: sorted(f.name for f in p.iterdir()) for p in list_requests(self._keeper.requests)}

    def kept_file(self, request_id: str, name: str) -> Path:
        """A file of a kept request a browser may fetch (not request.json: it names this machine's paths)."""
        if name not in VIEWABLE or not KEPT_ID.fullmatch(request_id):
            raise RequestError(404, "no such file")
        path = self._keeper.requests / f"{request_id[:4]}-{request_id[4:6]}-{request_id[6:8]}" / request_id / name
        if not path.is_file():
            raise RequestError(404, f"{request_id}/{name} is not kept (service.keep_requests keeps the newest)")
        return path

    def close(self) -> None:
        self._worker.shutdown(wait=True)
        self._keeper.close()


# -- HTTP ----------------------------------------------------------------------------------------


def http_app(service: PickService):
    """The FastAPI application (and the TCP server, started with it)."""

    @contextlib.asynccontextmanager
    async def lifespan(app):
        server = None
        if service.settings.tcp_port:
            server = await asyncio.start_server(
                lambda r, w: tcp_client(service, r, w),
                service.settings.host,
                service.settings.tcp_port,
                limit=service.max_bytes * 2,
            )
        try:
            yield
        finally:
            if server is not None:
                server.close()
                await server.wait_closed()

    app = FastAPI(
        title="binpick pick service",
        version=str(PICKS_VERSION),
        lifespan=lifespan,
        description="Picks for a capture of a bin: the poses of the parts and a collision-free grasp per part, ranked. "
        "Send `Authorization: Bearer <token>` when the service was started with a token.",
    )
    errors: dict[int | str, dict[str, Any]] = {
        code: {"model": ErrorAnswer} for code in (400, 401, 404, 409, 413, 429, 503)
    }

    @app.exception_handler(RequestError)
    async def refused(request: Request, exc: RequestError) -> JSONResponse:
        if request.url.path == "/picks":
            service.operator.refused(exc.status, service.public(str(exc)), request.query_params.get("part"))
        return JSONResponse({"error": service.public(str(exc))}, status_code=exc.status)

    def state() -> dict[str, Any]:
        return operator_state(service.health(), service.operator.recent(), service.kept_files())

    @app.get("/", response_class=HTMLResponse, summary="The operator page (read-only; ?token= offers the reload)")
    async def operator_page(request: Request):
        given = request.query_params.get("token")
        controls = service.token is None or given == service.token
        page = render_page(await run_in_threadpool(state), controls, given if controls else None)
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

    @app.get("/operator/state", summary="The operator page's figures as JSON")
    async def operator_figures():
        return await run_in_threadpool(state)

    @app.get("/requests/{request_id}/{name}", summary="A kept request's image, recording or pick list")
    async def kept(request_id: str, name: str):
        return FileResponse(service.kept_file(request_id, name), media_type=VIEWABLE.get(name))

    @app.post("/operator/reload", include_in_schema=False)
    async def operator_reload(request: Request):
        from urllib.parse import parse_qs

        given = parse_qs((await request.body()).decode(errors="replace")).get("token", [None])[0]
        service.check_token(given)
        await run_in_threadpool(service.reload)
        return RedirectResponse("/" + (f"?token={given}" if given else ""), status_code=303)

    def authorised(request: Request) -> None:
        value = request.headers.get("authorization", "")
        service.check_token(value[7:] if value.lower().startswith("bearer ") else None)

    @app.get("/health", response_model=Health, responses=errors)
    async def health(request: Request):
        authorised(request)
        return service.health()

    @app.post(
        "/reload",
        response_model=Health,
        responses=errors,
        summary="Load the project's parts again (a part trained or fine-tuned since the service started)",
    )
    async def reload(request: Request):
        authorised(request)
        return await run_in_threadpool(service.reload)

    upload_schema = {
        "requestBody": {
            "content": {
                "application/json": {"schema": PicksRequest.model_json_schema()},
                "application/octet-stream": {
                    "schema": {"type": "string", "format": "binary"},
                    "description": "the capture file; part, format and unit as query parameters",
                },
            }
        }
    }

    @app.post(
        "/picks",
        response_model=PicksAnswer,
        response_model_exclude_unset=True,
        responses=errors,
        openapi_extra=upload_schema,
        summary="Picks for one capture: JSON naming a file or the camera, or the capture file as the body",
    )
    async def picks(request: Request):
        authorised(request)
        service.check_rate()
        declared = request.headers.get("content-length")
        if declared is not None and int(declared) > service.max_bytes:
            raise RequestError(
                413,
                f"request of {int(declared) / 2**20:.1f} MB is over service.max_request_mb "
                f"{service.settings.max_request_mb:g}",
            )
        body = bytearray()
        async for chunk in request.stream():
            body += chunk
            if len(body) > service.max_bytes:
                raise RequestError(413, f"request is over service.max_request_mb {service.settings.max_request_mb:g}")
        if request.headers.get("content-type", "").startswith("application/json"):
            fields, payload = _json_object(bytes(body)), None
        else:
            fields, payload = dict(request.query_params), bytes(body) if body else None
        return await service.answer(_picks_request(fields), payload)

    return app


def _json_object(text: bytes) -> dict[str, Any]:
    try:
        fields = json.loads(text)
    except ValueError as exc:
        raise RequestError(400, f"not JSON: {exc}") from None
    if not isinstance(fields, dict):
        raise RequestError(400, "the request must be a JSON object")
    return fields


def _picks_request(fields: dict[str, Any]) -> PicksRequest:
    try:
        return PicksRequest.model_validate(fields)
    except ValidationError as exc:
        raise RequestError(400, validation_message(exc)) from None


async def tcp_client(service: PickService, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """One connection of the line protocol: a request per line, an answer per line (JSON for
    JSON, numbers for a text command: see _text_answer)."""
    connection: dict[str, str | None] = {"token": None}  # `TOKEN <t>` authorises the text commands that follow
    try:
        while True:
            try:
                line = await reader.readline()
            except (asyncio.LimitOverrunError, ValueError):
                writer.write(
                    json.dumps(
                        {"error": f"request line is over service.max_request_mb {service.settings.max_request_mb:g}"}
                    ).encode()
                    + b"\n"
                )
                break
            if not line:
                break
            if line.lstrip()[:1] in (b"{", b"["):
                writer.write(json.dumps(await _tcp_answer(service, line)).encode() + b"\n")
            else:
                writer.write((await _text_answer(service, line, connection)).encode() + b"\n")
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError):
        pass
    finally:
        with contextlib.suppress(Exception):
            writer.close()
            await writer.wait_closed()


async def _tcp_answer(service: PickService, line: bytes) -> dict[str, Any]:
    """{"health": true} and {"reload": true} (with "token" when one is set) or a PicksRequest."""
    fields: Any = None
    try:
        fields = _json_object(line)
        service.check_token(fields.get("token"))
        if fields.get("health"):
            return service.health()
        if fields.get("reload"):
            return await asyncio.get_running_loop().run_in_executor(None, service.reload)
        service.check_rate()
        request = _picks_request(fields)
        payload = None
        if request.data_b64 is not None:
            try:
                payload = base64.b64decode(request.data_b64, validate=True)
            except (ValueError, TypeError) as exc:
                raise RequestError(400, f"data_b64 is not base64: {exc}") from None
        return await service.answer(request, payload)
    except RequestError as exc:
        message = service.public(str(exc))
        service.operator.refused(exc.status, message, fields.get("part") if isinstance(fields, dict) else None)
        return {"error": message, "status": exc.status}


# The text commands' answer: a status, then the first pick's pregrasp, grasp, postgrasp and place
# poses, as URScript's socket_read_ascii_float reads them: "(n1,n2,...)", at most 30 numbers.
TEXT_WAYPOINTS = ("pregrasp", "grasp", "postgrasp", "place")


async def _text_answer(service: PickService, line: bytes, connection: dict[str, str | None]) -> str:
    """A robot controller's request, in words it can send without a JSON library:

        TOKEN <token>                      authorises this connection's later commands
        PICK <part> [<format>] [<path>]    the best pick of a camera frame (or of a capture file)

    <format> is ur (the default), abb, kuka or fanuc. The answer is one line of numbers in
    parentheses: status (1 a pick, 0 no part to pick, minus the HTTP status of a refusal, e.g.
    -404 for an unknown part) and four poses in that format (pregrasp, grasp, postgrasp, place;
    zeros when there is no pick, or no place planned): 25 numbers (29 for abb)."""
    from binpick.robot.pose_formats import FIELDS

    words = line.decode(errors="replace").split()
    fmt = "ur"
    try:
        if not words:
            raise RequestError(400, "empty command")
        command = words[0].upper()
        if command == "TOKEN" and len(words) == 2:
            connection["token"] = words[1]
            service.check_token(words[1])
            return _floats([1.0])
        if command != "PICK" or len(words) < 2:
            raise RequestError(400, "a text command is PICK <part> [<format>] [<path>] or TOKEN <token>")
        service.check_token(connection["token"])
        service.check_rate()
        rest = words[2:]
        if rest and rest[0].lower() in FIELDS:
            fmt = rest.pop(0).lower()
        fields: dict[str, Any] = {"part": words[1], "pose_format": fmt}
        fields.update({"path": " ".join(rest)} if rest else {"camera": True})
        answer = await service.answer(_picks_request(fields))
    except RequestError as exc:
        log.info("text command refused (%d): %s", exc.status, exc)
        service.operator.refused(exc.status, service.public(str(exc)), words[1] if len(words) > 1 else None)
        return _floats([-float(exc.status)] + [0.0] * len(FIELDS[fmt]) * len(TEXT_WAYPOINTS))
    numbers = [0.0] * len(FIELDS[fmt]) * len(TEXT_WAYPOINTS)
    if answer["picks"]:
        robot = answer["picks"][0]["robot"]
        numbers = [x for w in TEXT_WAYPOINTS for x in (robot.get(w) or [0.0] * len(FIELDS[fmt]))]
    return _floats([1.0 if answer["picks"] else 0.0, *numbers])


def _floats(values: list[float]) -> str:
    return "(" + ",".join(f"{round(v, 6) + 0.0:.6f}" for v in values) + ")"  # + 0.0: no "-0.000000"


def run_service(
    root: Path, params_path: Path, host: str | None = None, http_port: int | None = None, tcp_port: int | None = None
) -> None:
    """Load the parts, then serve until interrupted."""
    import uvicorn

    s = load_params(params_path).service
    s = s.model_copy(
        update={k: v for k, v in {"host": host, "http_port": http_port, "tcp_port": tcp_port}.items() if v is not None}
    )
    if s.host not in LOOPBACK and not os.environ.get(s.token_env):
        raise BinpickError(
            f"binding to {s.host} (beyond this machine) needs a token: set the {s.token_env} environment variable"
        )
    service = PickService(root, params_path)
    service.settings = s
    log.info(
        "answering on http://%s:%d%s", s.host, s.http_port, f" and tcp://{s.host}:{s.tcp_port}" if s.tcp_port else ""
    )
    try:
        uvicorn.Server(
            uvicorn.Config(http_app(service), host=s.host, port=s.http_port, log_level="warning", access_log=False)
        ).run()
    finally:
        service.close()


def openapi_schema() -> dict[str, Any]:
    """The service's OpenAPI schema without loading a project (for the documentation): the routes
    touch the service only when they answer, so none is given."""
    return http_app(typing.cast(PickService, None)).openapi()
