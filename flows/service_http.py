"""The pick service over HTTP (FastAPI): the routes of flows/service.py's docstring, the operator
page (flows/operator.py) and the kept requests' files; the TCP line protocol (flows/service_lines.py)
starts and stops with the application. `run_service` is what `binpick service` runs."""

from __future__ import annotations

import asyncio
import contextlib
import os
import typing
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from starlette.concurrency import run_in_threadpool

from binpick.errors import BinpickError
from binpick.io.picks import VERSION as PICKS_VERSION
from binpick.params import load_params
from flows.operator import REFRESH_S, operator_state, render_page
from flows.service import LOOPBACK, VIEWABLE, PickService, RequestError, json_object, log, picks_request
from flows.service_api import ErrorAnswer, Health, PicksAnswer, PicksRequest
from flows.service_lines import tcp_client


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
            return JSONResponse(
                {"error": service.refused(exc, request.query_params.get("part"))}, status_code=exc.status
            )
        return JSONResponse({"error": service.public(str(exc))}, status_code=exc.status)

    def state() -> dict[str, Any]:
        return operator_state(service.health(), service.operator.recent(), service.kept_files())

    @app.get("/", response_class=HTMLResponse, summary="The operator page (read-only; ?token= offers the reload)")
    async def operator_page(request: Request):
        given = request.query_params.get("token")
        controls = service.token is None or given == service.token
        try:  # ?refresh=0 holds the page still (for a screenshot or a slow look)
            refresh_s = min(max(int(request.query_params.get("refresh", REFRESH_S)), 0), 3600)
        except ValueError:
            refresh_s = REFRESH_S
        page = render_page(await run_in_threadpool(state), controls, given if controls else None, refresh_s)
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

    @app.get("/operator/state", summary="The operator page's figures as JSON")
    async def operator_figures():
        return await run_in_threadpool(state)

    @app.get("/requests/{request_id}/{name}", summary="A kept request's image, recording or pick list")
    async def kept(request_id: str, name: str):
        return FileResponse(service.kept_file(request_id, name), media_type=VIEWABLE.get(name))

    @app.post("/operator/reload", include_in_schema=False)
    async def operator_reload(request: Request):
        from urllib.parse import parse_qs, urlencode

        form = parse_qs((await request.body()).decode(errors="replace"))
        given = form.get("token", [None])[0]
        service.check_token(given)
        await run_in_threadpool(service.reload)
        # Back to the page as it was opened (its token, its refresh).
        back: dict[str, str] = {k: form[k][0] for k in ("token", "refresh") if k in form}
        return RedirectResponse("/" + (f"?{urlencode(back)}" if back else ""), status_code=303)

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
            fields, payload = json_object(bytes(body)), None
        else:
            fields, payload = dict(request.query_params), bytes(body) if body else None
        return await service.answer(picks_request(fields), payload)

    return app


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
