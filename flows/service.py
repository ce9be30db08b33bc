"""`binpick service`: a resident process answering "picks for this capture" for a robot cell.

It loads every trained part of the project once (part model, PPF model, network, grasps) and
answers over HTTP/JSON and over a plain TCP line protocol (one JSON request per line, one JSON
answer per line), on 127.0.0.1 by default. The answer is the picks.json document of the batch
pipeline (binpick.io.picks), plus the request's id, its timings per step and the poses. The
scene path is the library's (binpick.scene.process.process), the one the DVC stages and the
benchmarks call.

Requests are answered one at a time (two parts' models never fight over the cores); up to
service.max_queue more wait, further ones are refused as busy. A bad request gets an error answer
and the service goes on. Each answered request is kept for review in
<keep_dir>/requests/<date>/<id>/ (the capture, request.json, poses.json, picks.json and a rerun
recording) and logged to MLflow (experiment `service`), both after the answer is sent; the newest
service.keep_requests are kept.

HTTP:
  GET  /health                      {"status": "ok", "parts": [...], "answered": n, "uptime_s": s}
  POST /picks?part=P&format=zdf&unit=mm   the capture file as the body (application/octet-stream)
  POST /picks  {"part": P, "path": FILE, "unit": "mm"}   a capture file on this machine
  POST /picks  {"part": P, "camera": true}               a frame from the connected Zivid camera
TCP: the same JSON objects, one per line ({"health": true} for health; an upload as
  "data_b64" with "format"), each with "token" when one is required.
Errors: {"error": "..."} (HTTP 400 bad request, 401 token, 404 unknown part, 413 too large,
  429 rate, 503 busy).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import os
import queue
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
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from binpick.errors import BinpickError
from binpick.io.capture import CAPTURE_SUFFIXES, ImportOptions, load_capture
from binpick.io.picks import picks_document, write_picks_document
from binpick.io.poses import save_poses
from binpick.layout import Layout
from binpick.params import Params, ServiceParams, load_params
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds
from flows.learn import served_checkpoint

log = logging.getLogger("binpick.service")

UNITS = ("mm", "m", "in")
LOOPBACK = ("127.0.0.1", "localhost", "::1")


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


def load_parts(root: Path, params_path: Path) -> dict[str, Served]:
    """Every part of the project whose models are built (data/models/<part>/ part.npz, ppf.npz,
    grasps.json; its network when trained)."""
    base = load_params(params_path)
    served: dict[str, Served] = {}
    for name in base.parts:
        layout = Layout(root)
        needed = [layout.part_model(name), layout.ppf_model(name), layout.grasps(name)]
        if not all(p.is_file() for p in needed):
            log.warning("not serving %s: its models are not built (run make repro)", name)
            continue
        p = load_params(params_path, name)
        # The fine-tuned network when `binpick learn finetune` found it no worse (flows/learn.py).
        checkpoint = served_checkpoint(root, name)
        models = PartModels.load(p, needed[0], needed[1], checkpoint, needed[2], layout.verification(name))
        served[name] = Served(models, p, np.asarray(p.pick.T_base_from_cam) if p.pick.T_base_from_cam is not None else None)
        log.info("serving %s (%s, %d %s grasps)", name, f"segmentation ({checkpoint.name}) + registration" if models.segmenter and checkpoint else
                 "registration only", len(models.grasps or []), p.pick.gripper)
    if not served:
        raise BinpickError(f"no part of {params_path} has built models to serve: run `make repro` first")
    return served


class PickService:
    """The service's state: the loaded parts, the queue, the limits, the keeper of requests."""

    def __init__(self, root: Path, params_path: Path, keep_mlflow: bool = True):
        self.root = Path(root)
        self.params = load_params(params_path)
        self.settings: ServiceParams = self.params.service
        self.parts = load_parts(self.root, params_path)
        self.token = os.environ.get(self.settings.token_env) or None
        self.started = time.monotonic()
        self.answered = 0
        # One request at a time, always on the same thread: numerics on ever new threads grow
        # the allocator's per-thread arenas and the thread pools of torch and Open3D.
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="binpick-answer")
        self._waiting = 0
        self._count = threading.Lock()
        self._recent: deque[float] = deque()
        self._keeper = Keeper(self.root / self.settings.keep_dir, self.settings.keep_requests, self.params.tracking.mlflow_uri if keep_mlflow else None,
                              keep_mlflow)

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
        return {"status": "ok", "parts": sorted(self.parts), "answered": self.answered, "waiting": self._waiting,
                "uptime_s": round(time.monotonic() - self.started, 3)}

    # -- answering -----------------------------------------------------------------------------

    def answer(self, request: dict[str, Any], payload: bytes | None = None) -> dict[str, Any]:
        """The picks for one request (see the module's docstring); raises RequestError."""
        part = request.get("part")
        if not isinstance(part, str) or part not in self.parts:
            raise RequestError(404 if isinstance(part, str) else 400, f"unknown part {part!r} (serving: {', '.join(sorted(self.parts))})")
        unit = request.get("unit", "mm")
        if unit not in UNITS:
            raise RequestError(400, f"unit {unit!r} is not one of {', '.join(UNITS)}")
        with self._count:
            if self._waiting >= self.settings.max_queue + 1:
                raise RequestError(503, f"busy: {self._waiting} requests in progress or waiting")
            self._waiting += 1
        try:
            return self._worker.submit(self._answer, part, unit, request, payload).result()
        finally:
            with self._count:
                self._waiting -= 1

    def _capture_file(self, request: dict[str, Any], payload: bytes | None, folder: Path) -> Path:
        """The capture as a file: the upload written into the request's folder, a named file, or a camera frame."""
        if payload is not None:
            fmt = str(request.get("format", "")).lower().lstrip(".")
            if f".{fmt}" not in CAPTURE_SUFFIXES:
                raise RequestError(400, f"an uploaded capture needs its format: one of {', '.join(s.lstrip('.') for s in CAPTURE_SUFFIXES)}")
            path = folder / f"capture.{fmt}"
            path.write_bytes(payload)
            return path
        if request.get("path"):
            path = Path(str(request["path"]))
            path = path if path.is_absolute() else self.root / path
            allowed = [self.root, *(Path(f) for f in self.settings.capture_folders)]
            if not any(path.resolve().is_relative_to(a.resolve()) for a in allowed):
                raise RequestError(400, f"{path}: outside the project and service.capture_folders")
            if not path.is_file():
                raise RequestError(400, f"{path}: capture file not found")
            return path
        if request.get("camera"):
            from binpick.zivid_camera import grab_to_file

            path = folder / "capture.ply"
            try:
                grab_to_file(path, self.params.zivid_camera)
            except BinpickError as exc:
                raise RequestError(400, f"camera: {exc}") from None
            return path
        raise RequestError(400, "a request names a capture: an upload (with its format), a \"path\" or \"camera\": true")

    def _answer(self, part: str, unit: str, request: dict[str, Any], payload: bytes | None) -> dict[str, Any]:
        served = self.parts[part]
        t0 = time.perf_counter()
        stamp = datetime.now(UTC)
        request_id = f"{stamp:%Y%m%dT%H%M%S%f}-{part}"
        folder = self._keeper.folder(stamp, request_id)
        try:
            path = self._capture_file(request, payload, folder)
            t_read = time.perf_counter()
            try:
                frame = load_capture(path, ImportOptions(unit))
            except BinpickError as exc:
                raise RequestError(400, str(exc)) from None
            # Seeds from the capture's content, as the DVC stages take them: the same capture
            # gets the same answer here and when `binpick requests --add` runs it through them.
            seeds = SceneSeeds.of_capture(served.params.seed, frame.xyz_m, frame.rgb)
            t1 = time.perf_counter()
            try:
                result = process(frame.xyz_m, frame.rgb, frame.shape, served.models, seeds)
            except BinpickError as exc:
                raise RequestError(400, f"{path.name}: {exc}") from None
        except RequestError:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        t2 = time.perf_counter()
        assert result.picks is not None
        doc = picks_document(request_id, part, served.params.pick.gripper, result.picks, served.T_base_from_cam)
        timings = {"read_s": t1 - t_read, **result.timings_s, "pipeline_s": t2 - t1, "total_s": t2 - t0}
        doc["request_id"] = request_id
        doc["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
        doc["poses"] = [{"T_cam_from_model": np.asarray(p.T_cam_from_model).round(9).tolist(), "score": round(p.score, 6)} for p in result.poses]
        self.answered += 1
        self._keeper.keep(folder, path, doc, result, served, unit)
        return doc

    def close(self) -> None:
        self._worker.shutdown(wait=True)
        self._keeper.close()


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
        self._stream = None  # one rerun stream for every recording (a stream per file leaks threads)
        self._thread = threading.Thread(target=self._run, name="binpick-keeper", daemon=True)
        self._thread.start()

    def folder(self, stamp: datetime, request_id: str) -> Path:
        path = self.requests / f"{stamp:%Y-%m-%d}" / request_id
        path.mkdir(parents=True, exist_ok=True)
        return path

    def keep(self, folder: Path, capture: Path, doc: dict, result, served: Served, unit: str) -> None:
        self._jobs.put((folder, capture, doc, result, served, unit))

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

    def _keep(self, folder: Path, capture: Path, doc: dict, result, served: Served, unit: str) -> None:
        from stages.common import mlflow_run
        from stages.common.pick_recording import write_pick_recording

        if capture.parent != folder:  # a named file: keep a copy (a link where the disk allows)
            target = folder / f"capture{capture.suffix}"
            try:
                os.link(capture, target)
            except OSError:
                shutil.copyfile(capture, target)
        part = served.models.part
        write_picks_document(folder / "picks.json", {k: v for k, v in doc.items() if k not in ("timings_s", "poses", "request_id")})
        save_poses(folder / "poses.json", part.name, result.poses)
        (folder / "request.json").write_text(json.dumps({"request_id": doc["request_id"], "part": part.name, "timings_s": doc["timings_s"],
                                                         "counts": doc["counts"], "source": str(capture), "unit": unit}, indent=1) + "\n")
        if self._stream is None:
            import rerun as rr

            self._stream = rr.RecordingStream("binpick", recording_id="binpick-service")
        write_pick_recording(folder / "scene.rrd", doc["request_id"], result.cloud, part, result.poses, result.picks, served.params.pick.gripper,
                             served.params.pick, self._stream)
        if self.log_mlflow:
            with mlflow_run("service", doc["request_id"], self.mlflow_uri, {"part": part.name, "request_id": doc["request_id"]}):
                import mlflow

                mlflow.log_metrics({**doc["timings_s"], **doc["counts"],
                                    "score_mean": float(np.mean([p.score for p in result.poses])) if result.poses else 0.0})
        self._prune()

    def _prune(self) -> None:
        kept = list_requests(self.requests)
        for old in kept[self.limit:]:
            shutil.rmtree(old, ignore_errors=True)
            with contextlib.suppress(OSError):
                old.parent.rmdir()  # the day's folder, once empty


def list_requests(requests: Path) -> list[Path]:
    """Kept request folders, newest first."""
    if not requests.is_dir():
        return []
    return sorted((p for day in requests.iterdir() if day.is_dir() for p in day.iterdir() if p.is_dir()), key=lambda p: p.name, reverse=True)


# -- HTTP ----------------------------------------------------------------------------------------

def http_app(service: PickService):
    """The FastAPI application (and the TCP server, started with it)."""
    @contextlib.asynccontextmanager
    async def lifespan(app):
        server = None
        if service.settings.tcp_port:
            server = await asyncio.start_server(lambda r, w: tcp_client(service, r, w), service.settings.host, service.settings.tcp_port,
                                                limit=service.max_bytes * 2)
        try:
            yield
        finally:
            if server is not None:
                server.close()
                await server.wait_closed()

    app = FastAPI(title="binpick pick service", lifespan=lifespan)

    def error(exc: RequestError) -> JSONResponse:
        return JSONResponse({"error": str(exc)}, status_code=exc.status)

    def bearer(request: Request) -> str | None:
        value = request.headers.get("authorization", "")
        return value[7:] if value.lower().startswith("bearer ") else None

    @app.get("/health")
    async def health(request: Request):
        try:
            service.check_token(bearer(request))
        except RequestError as exc:
            return error(exc)
        return service.health()

    @app.post("/picks")
    async def picks(request: Request):
        try:
            service.check_token(bearer(request))
            service.check_rate()
            declared = request.headers.get("content-length")
            if declared is not None and int(declared) > service.max_bytes:
                raise RequestError(413, f"request of {int(declared) / 2**20:.1f} MB is over service.max_request_mb {service.settings.max_request_mb:g}")
            body = bytearray()
            async for chunk in request.stream():
                body += chunk
                if len(body) > service.max_bytes:
                    raise RequestError(413, f"request is over service.max_request_mb {service.settings.max_request_mb:g}")
            if request.headers.get("content-type", "").startswith("application/json"):
                try:
                    fields = json.loads(bytes(body))
                except ValueError as exc:
                    raise RequestError(400, f"not JSON: {exc}") from None
                if not isinstance(fields, dict):
                    raise RequestError(400, "the request must be a JSON object")
                payload = None
            else:
                fields = dict(request.query_params)
                payload = bytes(body) if body else None
            answer = await run_in_threadpool(service.answer, fields, payload)
        except RequestError as exc:
            return error(exc)
        return answer

    return app


async def tcp_client(service: PickService, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """One connection of the line protocol: a JSON request per line, a JSON answer per line."""
    try:
        while True:
            try:
                line = await reader.readline()
            except (asyncio.LimitOverrunError, ValueError):
                writer.write(json.dumps({"error": f"request line is over service.max_request_mb {service.settings.max_request_mb:g}"}).encode() + b"\n")
                break
            if not line:
                break
            answer = await asyncio.get_running_loop().run_in_executor(None, _tcp_answer, service, line)
            writer.write(json.dumps(answer).encode() + b"\n")
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError):
        pass
    finally:
        with contextlib.suppress(Exception):
            writer.close()
            await writer.wait_closed()


def _tcp_answer(service: PickService, line: bytes) -> dict[str, Any]:
    try:
        try:
            request = json.loads(line)
        except ValueError as exc:
            raise RequestError(400, f"not JSON: {exc}") from None
        if not isinstance(request, dict):
            raise RequestError(400, "the request must be a JSON object")
        service.check_token(request.get("token"))
        if request.get("health"):
            return service.health()
        service.check_rate()
        payload = None
        if "data_b64" in request:
            try:
                payload = base64.b64decode(request["data_b64"], validate=True)
            except (ValueError, TypeError) as exc:
                raise RequestError(400, f"data_b64 is not base64: {exc}") from None
        return service.answer(request, payload)
    except RequestError as exc:
        return {"error": str(exc), "status": exc.status}


def run_service(root: Path, params_path: Path, host: str | None = None, http_port: int | None = None, tcp_port: int | None = None) -> None:
    """Load the parts, then serve until interrupted."""
    import uvicorn

    s = load_params(params_path).service
    s = s.model_copy(update={k: v for k, v in {"host": host, "http_port": http_port, "tcp_port": tcp_port}.items() if v is not None})
    if s.host not in LOOPBACK and not os.environ.get(s.token_env):
        raise BinpickError(f"binding to {s.host} (beyond this machine) needs a token: set the {s.token_env} environment variable")
    service = PickService(root, params_path)
    service.settings = s
    log.info("answering on http://%s:%d%s", s.host, s.http_port, f" and tcp://{s.host}:{s.tcp_port}" if s.tcp_port else "")
    try:
        uvicorn.Server(uvicorn.Config(http_app(service), host=s.host, port=s.http_port, log_level="warning", access_log=False)).run()
    finally:
        service.close()
