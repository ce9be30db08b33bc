"""The pick service's operator page: what the cell is doing, at a glance, in a browser.

`binpick service` serves it at `/` (plain server-rendered HTML that refreshes itself; no
JavaScript, nothing fetched from the internet) and the same figures as JSON at /operator/state:
the parts served and the ones not served with why, the latest kept request's image with the parts
found and the chosen pick drawn on it, the last requests with their timings and outcome, refusals
and unpicked parts counted by reason, picks per hour and the failure rate over the last hour, and
a link to each kept request's rerun recording. The page is read-only; opened with
`?token=<the service's token>` (or when the service has no token) it also offers to reload the parts.
"""

from __future__ import annotations

import html
import threading
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from typing import Any
from urllib.parse import quote

# The statistics cover the last hour; the table shows the newest ROWS requests.
WINDOW_S = 3600.0
ROWS = 20
# Picks per hour over less than this much history would swing wildly on the first request.
MIN_SPAN_S = 60.0
REFRESH_S = 5

HTTP_REASONS = {
    400: "bad request",
    401: "missing or wrong token",
    404: "unknown part",
    409: "reload refused",
    413: "request too large",
    429: "over the rate limit",
    503: "busy",
}


@dataclass(frozen=True)
class Outcome:
    """One request as the operator sees it."""

    at: float  # time.time() when answered or refused
    request_id: str | None
    part: str | None
    status: int  # 200 answered, else the refusal's HTTP status
    n_poses: int = 0
    n_picks: int = 0
    total_s: float | None = None
    why: str = ""  # the refusal, or the first reason a part was not picked
    unpicked: tuple[str, ...] = ()

    @property
    def outcome(self) -> str:
        if self.status != 200:
            return "refused"
        return "pick" if self.n_picks else "no pick"


class OperatorLog:
    """The requests of the last hour, in memory (a restart starts it afresh; the kept requests
    on disk stay)."""

    def __init__(self) -> None:
        self._items: deque[Outcome] = deque()
        self._lock = threading.Lock()

    def answered(self, doc: dict[str, Any]) -> None:
        unpicked = tuple(u["reason"] for u in doc.get("unpicked", []))
        self._add(
            Outcome(
                time.time(),
                doc["request_id"],
                doc.get("part") or ",".join(doc.get("parts", [])),
                200,
                len(doc.get("poses", [])),
                len(doc["picks"]),
                doc.get("timings_s", {}).get("total_s"),
                "" if doc["picks"] else (unpicked[0] if unpicked else "no part found"),
                unpicked,
            )
        )

    def refused(self, status: int, message: str, part: str | None = None) -> None:
        self._add(Outcome(time.time(), None, part, status, why=message))

    def _add(self, item: Outcome) -> None:
        with self._lock:
            self._items.append(item)
            while self._items and item.at - self._items[0].at > WINDOW_S:
                self._items.popleft()

    def recent(self) -> list[Outcome]:
        now = time.time()
        with self._lock:
            return [o for o in self._items if now - o.at <= WINDOW_S]


def summarise(items: list[Outcome], now: float) -> dict[str, Any]:
    """The last hour's figures: requests, picks per hour (requests answered with a pick, per hour of
    the time since the first request of the window, at least MIN_SPAN_S), the failure rate (refused
    or nothing to pick, of all requests), refusals and unpicked parts counted by reason."""
    picked = sum(o.outcome == "pick" for o in items)
    span_s = max(now - min((o.at for o in items), default=now), MIN_SPAN_S)
    answered = [o.total_s for o in items if o.total_s is not None]
    return {
        "requests_last_hour": len(items),
        "picks_per_hour": round(picked * 3600.0 / min(span_s, WINDOW_S), 1),
        "failure_rate": round((len(items) - picked) / len(items), 3) if items else 0.0,
        "total_s_median": round(sorted(answered)[len(answered) // 2], 3) if answered else None,
        "refusals": dict(
            Counter(f"{o.status} {HTTP_REASONS.get(o.status, 'refused')}" for o in items if o.status != 200)
        ),
        "unpicked": dict(Counter(r for o in items for r in o.unpicked).most_common(10)),
    }


def operator_state(health: dict[str, Any], items: list[Outcome], kept: dict[str, list[str]]) -> dict[str, Any]:
    """What the page shows (and /operator/state answers); kept: request id -> the files kept of it."""
    now = time.time()
    rows = []
    for o in reversed(items[-ROWS:]):
        row = {k: v for k, v in asdict(o).items() if k != "unpicked"}
        row["at"] = datetime.fromtimestamp(o.at, UTC).isoformat(timespec="seconds")
        row["outcome"] = o.outcome
        row["files"] = kept.get(o.request_id or "", [])
        rows.append(row)
    latest = next((i for i, files in kept.items() if "overlay.png" in files), None)
    return {**health, **summarise(items, now), "latest_image": latest, "requests": rows}


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def render_page(state: dict[str, Any], controls: bool, token: str | None, refresh_s: int = REFRESH_S) -> str:
    """The operator page (HTML) of operator_state's figures; controls: offer the reload button;
    refresh_s: the page reloads itself this often (0: never)."""
    not_served = "".join(f"<li>{_e(p)}: {_e(why)}</li>" for p, why in state["not_served"].items())

    def counted(counts: dict[str, int]) -> str:
        rows = "".join(f"<tr><td>{_e(k)}</td><td>{v}</td></tr>" for k, v in counts.items())
        return f"<table>{rows}</table>" if rows else "<p>none</p>"

    latest = state["latest_image"]
    image = (
        f'<figure><img id="latest" src="/requests/{quote(latest)}/overlay.png" alt="latest capture with its picks">'
        f"<figcaption>{_e(latest)}: the parts found, tinted, and the chosen pick (ring: grasp, line: approach)"
        "</figcaption></figure>"
        if latest
        else "<p>No kept request with an image yet (an organized capture is needed; service.keep_requests &gt; 0).</p>"
    )
    rows = []
    for r in state["requests"]:
        links = " ".join(
            f'<a href="/requests/{quote(r["request_id"])}/{quote(name)}">{_e(name)}</a>'
            for name in r["files"]
            if name in ("scene.rrd", "picks.json", "overlay.png")
        )
        total = "" if r["total_s"] is None else f"{r['total_s']:.2f}"
        rows.append(
            f'<tr class="{_e(r["outcome"]).replace(" ", "-")}"><td>{_e(r["at"])}</td><td>{_e(r["part"] or "")}</td>'
            f"<td>{_e(r['outcome'])}</td><td>{r['n_poses']}</td><td>{r['n_picks']}</td>"
            f"<td>{total}</td><td>{_e(r['why'])}</td><td>{links}</td></tr>"
        )
    table = (
        '<table id="requests"><thead><tr><th>time (UTC)</th><th>part</th><th>outcome</th><th>poses</th>'
        "<th>picks</th><th>total s</th><th>why</th><th>kept</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table>"
        if rows
        else '<p id="no-requests">No request yet.</p>'
    )
    hidden = f'<input type="hidden" name="token" value="{_e(token)}">' if token else ""
    if refresh_s != REFRESH_S:
        hidden += f'<input type="hidden" name="refresh" value="{refresh_s}">'
    reload_form = (
        f'<form method="post" action="/operator/reload">{hidden}<button>Reload the parts</button></form>'
        if controls
        else "<p>Read-only: open this page with ?token=… to reload the parts.</p>"
    )
    median = state["total_s_median"]
    refresh = f'<meta http-equiv="refresh" content="{refresh_s}">' if refresh_s > 0 else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">{refresh}
<title>binpick: cell</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }}
td, th {{ border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; font-size: 0.9em; }}
tr.refused td {{ background: #fde2e2; }} tr.no-pick td {{ background: #fff4d6; }}
.figures span {{ display: inline-block; margin-right: 2em; font-size: 1.2em; }}
img {{ max-width: 100%; border: 1px solid #999; }}
section {{ margin-bottom: 1.2em; }}
</style></head><body>
<h1>binpick cell</h1>
<section class="figures">
<span>picks per hour: <b id="picks-per-hour">{state["picks_per_hour"]}</b></span>
<span>failure rate (last hour): <b id="failure-rate">{100 * state["failure_rate"]:.0f} %</b></span>
<span>requests (last hour): <b>{state["requests_last_hour"]}</b></span>
<span>median answer: <b>{"-" if median is None else f"{median:.2f} s"}</b></span>
</section>
<section><h2>Parts</h2><p>served: <b id="parts">{_e(", ".join(state["parts"]))}</b>
(answered {state["answered"]}, waiting {state["waiting"]}, up {state["uptime_s"] / 3600:.1f} h)</p>
{f"<p>not served:</p><ul>{not_served}</ul>" if not_served else ""}{reload_form}</section>
<section><h2>Latest capture</h2>{image}</section>
<section><h2>Last requests</h2>{table}</section>
<section><h2>Refusals (last hour)</h2>{counted(state["refusals"])}
<h2>Why parts were not picked (last hour)</h2>{counted(state["unpicked"])}</section>
<p><a href="/operator/state">these figures as JSON</a> · <a href="/docs">the API</a></p>
</body></html>
"""
