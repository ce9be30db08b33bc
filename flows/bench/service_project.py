"""A `binpick service` for the scene benchmark and the soak test: a temporary project folder
holding the benchmark parts' models, the service started on it as a process of its own, and a
client of its TCP line protocol."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO, Any

from binpick.errors import BinpickError
from binpick.io.grasps import save_grasps
from binpick.io.part_model import save_part_model
from binpick.io.ppf_model import save_ppf_model
from binpick.layout import Layout
from binpick.params import Params
from binpick.scene.process import PartModels
from flows.bench import free_port

START_TIMEOUT_S = 300.0


def bench_overrides(p: Params) -> dict:
    """A part entry's overrides that make the project's settings the benchmark's for that part."""
    imp = p.import_capture
    return {
        "import_capture": {
            k: getattr(imp, k)
            for k in ("voxel_size_m", "normal_radius_m", "plane_threshold_m", "keep_above_plane_m", "max_range_m")
        }
    }


class ServiceProject:
    """A temporary project folder holding the benchmark parts' models, and a `binpick service`
    process answering for it."""

    def __init__(
        self,
        root: Path,
        settings_text: str,
        entries: dict[str, dict],
        models: dict[str, PartModels],
        checkpoints: dict[str, Path],
    ):
        from binpick.params import _edit

        self.root = root
        (root / "params.yaml").write_text(settings_text)
        (root / "dvc.yaml").write_text("stages: {}\n")

        def add_parts(doc) -> None:
            for name, entry in entries.items():
                if name in doc["parts"]:
                    doc["parts"][name].update({k: v for k, v in entry.items() if k not in ("mesh", "unit")})
                else:
                    doc["parts"][name] = entry

        _edit(root / "params.yaml", add_parts)
        layout = Layout(root)
        for name, m in models.items():
            layout.part_folder(name).mkdir(parents=True, exist_ok=True)
            save_part_model(layout.part_model(name), m.part)
            save_ppf_model(layout.ppf_model(name), m.ppf)
            assert m.grasps is not None
            oval = m.pick_params is not None and m.pick_params.suction.oval
            save_grasps(layout.grasps(name), name, {m.grasps.kind: m.grasps}, "generated", oval)
            if name in checkpoints and checkpoints[name].is_file():
                layout.network_folder(name).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(checkpoints[name], layout.checkpoint(name))
                if Layout.verification_of(checkpoints[name]).is_file():
                    shutil.copyfile(Layout.verification_of(checkpoints[name]), layout.verification(name))
        self.http_port, self.tcp_port = free_port(), free_port()
        self.process: subprocess.Popen | None = None
        self.log_file: IO[str] | None = None
        self._client: Any = None  # httpx.Client, made on the first request

    def start(self) -> float:
        """Start the service; returns the moment it was started (time.perf_counter())."""
        env = {**os.environ, "BINPICK_TOKEN": ""}
        # Its log goes to a file: a pipe nobody reads fills up and stops the service at a log line.
        self.log_file = open(self.root / "service.log", "w")  # noqa: SIM115 - closed in stop()
        t0 = time.perf_counter()
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "flows.cli",
                "service",
                "--http-port",
                str(self.http_port),
                "--tcp-port",
                str(self.tcp_port),
            ],
            cwd=self.root,
            env=env,
            stdout=self.log_file,
            stderr=subprocess.STDOUT,
            text=True,
        )
        return t0

    def wait_until_up(self) -> None:
        import httpx

        deadline = time.perf_counter() + START_TIMEOUT_S
        while time.perf_counter() < deadline:
            assert self.process is not None
            if self.process.poll() is not None:
                last = (self.root / "service.log").read_text().strip().splitlines()[-1:]
                raise BinpickError(f"the service exited: {' '.join(last) or 'no message'}")
            try:
                httpx.get(f"http://127.0.0.1:{self.http_port}/health", timeout=1.0)
                return
            except httpx.HTTPError:
                time.sleep(0.05)
        raise BinpickError(f"the service did not answer within {START_TIMEOUT_S:.0f} s")

    def http(self, part: str, capture: Path) -> dict:
        import httpx

        # One client kept open, as a cell's controller keeps its connection (and as the line
        # protocol's client does): a client per request spent 30 ms building its TLS context
        # and opened a new connection each time.
        if self._client is None:
            self._client = httpx.Client(timeout=600)
        return self._client.post(
            f"http://127.0.0.1:{self.http_port}/picks", json={"part": part, "path": str(capture)}
        ).json()

    def rss_mb(self) -> float:
        assert self.process is not None
        import psutil

        return psutil.Process(self.process.pid).memory_info().rss / 2**20

    def stop(self) -> None:
        if self._client is not None:
            self._client.close()
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        if self.log_file is not None:
            self.log_file.close()


class LineClient:
    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=600)
        self.stream = self.sock.makefile("rwb")

    def ask(self, request: dict) -> dict:
        self.stream.write(json.dumps(request).encode() + b"\n")
        self.stream.flush()
        return json.loads(self.stream.readline())

    def close(self) -> None:
        self.stream.close()
        self.sock.close()
