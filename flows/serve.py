"""`binpick serve`: the watcher flow on a schedule, served from this machine.

The schedule's runs live on a Prefect server: the one PREFECT_API_URL names (a team's shared
server), else a local one this process starts on the loopback interface and stops on exit
(state in data/prefect, UI at the printed address). Flow runs execute here, one at a time, in
the project folder, because every run drives this project's DVC pipeline.
"""

import contextlib
import logging
import os
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

from binpick.errors import BinpickError
from binpick.params import OrchestrationParams

log = logging.getLogger("binpick.serve")

DEPLOYMENT = "scheduled"


def _healthy(api_url: str) -> bool:
    """A Prefect server answers at api_url: /health says `true` and /admin/version a version.
    Any other program on the port (a web server answering 200 to everything) is not one."""
    import json

    try:
        with urllib.request.urlopen(f"{api_url}/health", timeout=2) as response:
            if response.status != 200 or json.loads(response.read() or b"null") is not True:
                return False
        with urllib.request.urlopen(f"{api_url}/admin/version", timeout=2) as response:
            return isinstance(json.loads(response.read() or b"null"), str)
    except (OSError, ValueError):
        return False


def _port_taken(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


@contextlib.contextmanager
def local_server(port: int, startup_timeout_s: float = 120.0) -> Iterator[str]:
    """`prefect server start` on 127.0.0.1:<port> for the duration; yields its API URL."""
    api_url = f"http://127.0.0.1:{port}/api"
    if _healthy(api_url):
        log.info("using the Prefect server already running at %s", api_url)
        yield api_url
        return
    if _port_taken(port):
        raise BinpickError(
            f"port {port} on 127.0.0.1 is in use by a program that is not a Prefect server: choose another with --port"
        )
    cmd = [
        sys.executable,
        "-m",
        "prefect",
        "server",
        "start",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--analytics-off",
    ]
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    server = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + startup_timeout_s
        while not _healthy(api_url):
            if server.poll() is not None:
                tail = (server.stderr.read() if server.stderr else "").strip().splitlines()[-1:]
                raise BinpickError(
                    f"the local Prefect server did not start on port {port}: {tail[0] if tail else 'no output'}"
                )
            if time.monotonic() > deadline:
                raise BinpickError(
                    f"the local Prefect server did not answer at {api_url} within {startup_timeout_s:.0f} s"
                )
            time.sleep(0.5)
        log.info("local Prefect server at %s (UI: http://127.0.0.1:%d)", api_url, port)
        yield api_url
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()


def schedule_for(orchestration: OrchestrationParams, interval_s: float | None):
    """The cron schedule from params, or a fixed interval (tests, trying things out)."""
    from prefect.schedules import Cron, Interval

    if interval_s:
        return Interval(timedelta(seconds=interval_s))
    return Cron(orchestration.schedule_cron, timezone=orchestration.schedule_timezone)


def serve_watcher(
    root: Path, orchestration: OrchestrationParams, interval_s: float | None = None, port: int = 4200
) -> None:
    """Serve the watcher flow on its schedule until interrupted."""
    shared = os.environ.get("PREFECT_API_URL")
    with contextlib.nullcontext(shared) if shared else local_server(port) as api_url:
        # Set before Prefect reads its settings, and inherited by the flow-run processes.
        os.environ["PREFECT_API_URL"] = api_url
        from prefect.settings import PREFECT_API_URL, temporary_settings
        from prefect.types.entrypoint import EntrypointType

        from flows.watcher import watch_parts

        schedule = schedule_for(orchestration, interval_s)
        when = (
            f"every {interval_s:g} s"
            if interval_s
            else f"cron '{orchestration.schedule_cron}' ({orchestration.schedule_timezone})"
        )
        log.info("serving watch-parts/%s %s against %s; Ctrl-C stops", DEPLOYMENT, when, api_url)
        os.chdir(root)  # flow runs start in the project, which holds their entry point and DVC
        with temporary_settings(updates={PREFECT_API_URL: api_url}):
            watch_parts.serve(
                name=DEPLOYMENT,
                schedules=[schedule],
                parameters={"root": str(root)},
                limit=1,
                pause_on_shutdown=False,
                print_starting_message=False,
                # by module, so that the flow-run process imports the installed flows package
                entrypoint_type=EntrypointType.MODULE_PATH,
                description="Registers new meshes in data/parts/ and trains every part that is not up to date.",
            )
