"""A client of `binpick service` for a cell's own Python program: copy this one file, it needs only
Python's standard library (3.9 or newer).

    from binpick_client import PickClient   # or: from binpick.client import PickClient

    service = PickClient("http://192.168.0.10:8765", token=None)
    answer = service.picks_from_file("t_joint", "bin.zdf", pose_format="ur")
    for pick in answer["picks"]:
        print(pick["robot"]["grasp"])           # p[x, y, z, rx, ry, rz] for a UR's movel

Every tool pose of an answer is in the robot's base frame under `base` (4 x 4 matrices, metres)
and, with a pose_format, under `robot` in that controller's convention (`pose_fields` names the
numbers). The answer's schema is the service's /openapi.json.

From a shell: python binpick_client.py URL PART CAPTURE [--format ur] [--unit mm] [--token T]
"""

from __future__ import annotations

import argparse
import json
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path


class PickServiceError(Exception):
    """The service refused a request: its HTTP status and its one-line reason."""

    def __init__(self, status: int, message: str):
        super().__init__(f"{status}: {message}")
        self.status = status
        self.message = message


class PickClient:
    """Talks HTTP/JSON to one pick service."""

    def __init__(self, url: str, token: str | None = None, timeout_s: float = 120.0):
        self.url = url.rstrip("/")
        self.token = token
        self.timeout_s = timeout_s

    def health(self) -> dict:
        """The parts served, the parts not served and why, requests answered."""
        return self._call("GET", "/health")

    def picks_from_file(self, part: str, capture: str | Path, unit: str = "mm", pose_format: str | None = None) -> dict:
        """Picks for a capture file on this machine, uploaded (its suffix is its format)."""
        capture = Path(capture)
        query = {"part": part, "format": capture.suffix.lstrip("."), "unit": unit}
        if pose_format:
            query["pose_format"] = pose_format
        return self._call(
            "POST", "/picks?" + urllib.parse.urlencode(query), capture.read_bytes(), "application/octet-stream"
        )

    def picks_from_camera(self, part: str, pose_format: str | None = None) -> dict:
        """Picks for a frame the service grabs from its connected camera."""
        return self._json_picks({"part": part, "camera": True, "pose_format": pose_format})

    def picks_at(self, part: str, path: str, unit: str = "mm", pose_format: str | None = None) -> dict:
        """Picks for a capture file on the service's machine (inside its project or capture folders)."""
        return self._json_picks({"part": part, "path": path, "unit": unit, "pose_format": pose_format})

    def _json_picks(self, fields: dict) -> dict:
        body = json.dumps({k: v for k, v in fields.items() if v is not None}).encode()
        return self._call("POST", "/picks", body, "application/json")

    def _call(self, method: str, path: str, body: bytes | None = None, content_type: str | None = None) -> dict:
        headers = {"Content-Type": content_type} if content_type else {}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        request = urllib.request.Request(self.url + path, data=body, headers=headers, method=method)
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                return json.loads(response.read())
        except urllib.error.HTTPError as exc:
            try:
                message = json.loads(exc.read()).get("error", exc.reason)
            except ValueError:
                message = exc.reason
            raise PickServiceError(exc.code, str(message)) from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Ask a binpick service for the picks of one capture file.")
    parser.add_argument("url", help="the service, e.g. http://127.0.0.1:8765")
    parser.add_argument("part")
    parser.add_argument("capture", type=Path)
    parser.add_argument("--format", dest="pose_format", choices=["matrix", "ur", "abb", "kuka", "fanuc"])
    parser.add_argument("--unit", default="mm", choices=["mm", "m", "in"])
    parser.add_argument("--token")
    args = parser.parse_args(argv)
    if not args.capture.is_file():
        sys.stderr.write(f"error: {args.capture}: capture file not found\n")
        return 2
    try:
        answer = PickClient(args.url, args.token).picks_from_file(args.part, args.capture, args.unit, args.pose_format)
    except PickServiceError as exc:
        sys.stderr.write(f"error: {exc}\n")
        return 1
    except OSError as exc:
        sys.stderr.write(f"error: {args.url}: {exc}\n")
        return 1
    sys.stdout.write(json.dumps(answer, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
