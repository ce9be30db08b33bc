"""The pick service's TCP line protocol: a request per line, an answer per line. JSON objects
(the HTTP API's requests, {"health": true}, {"reload": true}) get JSON answers; a robot
controller without JSON sends words (`PICK <part> [format]`, `TOKEN <token>`) and reads numbers."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
from typing import Any

from flows.service import PickService, RequestError, json_object, log, picks_request


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
        fields = json_object(line)
        service.check_token(fields.get("token"))
        if fields.get("health"):
            return service.health()
        if fields.get("reload"):
            return await asyncio.get_running_loop().run_in_executor(None, service.reload)
        service.check_rate()
        request = picks_request(fields)
        payload = None
        if request.data_b64 is not None:
            try:
                payload = base64.b64decode(request.data_b64, validate=True)
            except (ValueError, TypeError) as exc:
                raise RequestError(400, f"data_b64 is not base64: {exc}") from None
        return await service.answer(request, payload)
    except RequestError as exc:
        part = fields.get("part") if isinstance(fields, dict) else None
        return {"error": service.refused(exc, part), "status": exc.status}


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
    no_pose = [0.0] * len(FIELDS[fmt])
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
            no_pose = [0.0] * len(FIELDS[fmt])
        fields: dict[str, Any] = {"part": words[1], "pose_format": fmt}
        fields.update({"path": " ".join(rest)} if rest else {"camera": True})
        answer = await service.answer(picks_request(fields))
    except RequestError as exc:
        log.info("text command refused (%d): %s", exc.status, exc)
        service.refused(exc, words[1] if len(words) > 1 else None)
        return _floats([-float(exc.status)] + no_pose * len(TEXT_WAYPOINTS))
    robot = answer["picks"][0]["robot"] if answer["picks"] else {}
    numbers = [x for w in TEXT_WAYPOINTS for x in (robot.get(w) or no_pose)]
    return _floats([1.0 if answer["picks"] else 0.0, *numbers])


def _floats(values: list[float]) -> str:
    return "(" + ",".join(f"{round(v, 6) + 0.0:.6f}" for v in values) + ")"  # + 0.0: no "-0.000000"
