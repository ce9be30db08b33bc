"""`binpick bench report DIR`: the benchmark JSON files of a folder as a page of plots.

Every `binpick bench ...` file has its per-part figures under "parts" (some also at the top
level, for all parts together); the report reads them by their key names, so a new benchmark's
keys join the plots they belong to without code here:
- precision and recall per part: keys ending in `precision` or `recall`;
- cycle time distributions: lists of seconds, keys ending in `cycle_s`;
- timings per step: keys ending in `_s_median` (and `_s` numbers);
- picks per hour: `picks_per_hour` (and its `baseline_`).
It writes one PNG per kind of plot and index.html (the page) beside them, plus plots.md, the
same page as Markdown for the documentation site. Training curves stay in MLflow.
"""

from __future__ import annotations

import html
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from binpick.errors import BinpickError, InputError

log = logging.getLogger(__name__)

ALL_PARTS = "all parts"


@dataclass(frozen=True)
class Figure:
    """One number (or list of numbers) of one benchmark file."""

    bench: str  # the file's stem
    part: str  # a part's name, or ALL_PARTS for the file's top-level figures
    key: str
    value: float | list[float]


def _numbers(figures: dict[str, Any], bench: str, part: str) -> list[Figure]:
    out = []
    for key, value in figures.items():
        if isinstance(value, bool):
            continue
        if isinstance(value, int | float):
            out.append(Figure(bench, part, key, float(value)))
        elif isinstance(value, list) and value and all(isinstance(v, int | float) for v in value):
            out.append(Figure(bench, part, key, [float(v) for v in value]))
    return out


def collect(folder: Path) -> tuple[list[Figure], dict[str, dict]]:
    """The figures of every *.json benchmark file in folder, and each file's `machine`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "not a folder of benchmark JSON files")
    files = sorted(folder.glob("*.json"))
    if not files:
        raise InputError(folder, "has no benchmark JSON files (binpick bench ... --out writes them)")
    figures: list[Figure] = []
    machines: dict[str, dict] = {}
    for path in files:
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(path, f"not a benchmark JSON file ({exc})") from None
        if not isinstance(doc, dict):
            raise InputError(path, "not a benchmark JSON file (expected an object)")
        bench = path.stem
        figures += _numbers(doc, bench, ALL_PARTS)
        parts = doc.get("parts")
        if isinstance(parts, dict):
            for part, per in parts.items():
                if isinstance(per, dict):
                    figures += _numbers(per, bench, part)
        if isinstance(doc.get("machine"), dict):
            machines[bench] = doc["machine"]
    return figures, machines


def _select(figures: list[Figure], wanted: Callable[[str], bool], lists: bool) -> list[Figure]:
    return [f for f in figures if wanted(f.key) and isinstance(f.value, list) == lists]


def _is_quality(key: str) -> bool:
    return key.endswith(("precision", "recall")) and not key.startswith("baseline_")


def _is_step(key: str) -> bool:
    skip = ("cycle_s_median", "request_gap_s")
    return key.endswith(("_s_median", "_s")) and not key.startswith("baseline_") and key not in skip


def _grouped_bars(ax, groups: list[str], series: dict[str, dict[str, float]], ylabel: str) -> None:
    """Bars for each group (x) and series (colour): series[name][group]."""
    n = max(len(series), 1)
    width = 0.8 / n
    for i, (name, values) in enumerate(series.items()):
        xs = [g + (i - (n - 1) / 2) * width for g in range(len(groups))]
        ax.bar(xs, [values.get(g, 0.0) for g in groups], width, label=name)
    ax.set_xticks(range(len(groups)), groups, rotation=20, ha="right")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))


def _parts_last(part: str) -> tuple[bool, str]:
    """The parts in name order, the figures over all parts after them."""
    return part == ALL_PARTS, part


def _per_bench(
    plt,
    figures: list[Figure],
    x_of: Callable[[Figure], str],
    series_of: Callable[[Figure], str],
    ylabel: str,
    x_order: Callable[[set[str]], list[str]],
):
    """One panel of grouped bars per benchmark file: groups along x by x_of, a colour per
    series_of. Returns the figure and its panels."""
    benches = sorted({f.bench for f in figures})
    fig, axes = plt.subplots(len(benches), 1, figsize=(9, 3.4 * len(benches)), squeeze=False)
    for ax, bench in zip(axes[:, 0], benches, strict=True):
        mine = [f for f in figures if f.bench == bench]
        series: dict[str, dict[str, float]] = {}
        for f in mine:
            series.setdefault(series_of(f), {})[x_of(f)] = float(f.value)  # type: ignore[arg-type]
        _grouped_bars(ax, x_order({x_of(f) for f in mine}), series, ylabel)
        ax.set_title(bench)
    return fig, list(axes[:, 0])


def report(folder: Path, out: Path) -> list[Path]:
    """Write the plots of folder's benchmark files into out (PNGs, index.html, plots.md); the PNGs written."""
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    figures, machines = collect(folder)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[tuple[Path, str]] = []

    def save(fig, name: str, title: str) -> None:
        path = out / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append((path, title))

    quality = _select(figures, _is_quality, lists=False)
    if quality:
        fig, axes = _per_bench(
            plt, quality, lambda f: f.part, lambda f: f.key, "fraction", lambda parts: sorted(parts, key=_parts_last)
        )
        for ax in axes:
            ax.set_ylim(0, 1.05)
        save(fig, "precision_recall.png", "Precision and recall per part")

    cycles = _select(figures, lambda k: k.endswith("cycle_s"), lists=True)
    if cycles:
        fig, ax = plt.subplots(figsize=(9, 0.5 * len(cycles) + 1.5))
        ax.boxplot([f.value for f in cycles], orientation="horizontal")
        labels = [f"{f.bench}: {f.part}" + ("" if f.key == "cycle_s" else f" ({f.key})") for f in cycles]
        ax.set_yticks(range(1, len(cycles) + 1), labels)
        ax.set_xlabel("seconds per cycle")
        save(fig, "cycle_times.png", "Cycle time distributions")

    steps = _select(figures, _is_step, lists=False)
    if steps:
        fig, _ = _per_bench(plt, steps, lambda f: f.key, lambda f: f.part, "seconds", sorted)
        save(fig, "step_timings.png", "Timings per step")

    rates = _select(figures, lambda k: k in ("picks_per_hour", "baseline_picks_per_hour"), lists=False)
    if rates:
        groups = sorted({f"{f.bench}: {f.part}" for f in rates})
        series: dict[str, dict[str, float]] = {}
        for f in rates:
            series.setdefault(f.key, {})[f"{f.bench}: {f.part}"] = float(f.value)  # type: ignore[arg-type]
        fig, ax = plt.subplots(figsize=(9, 3.6))
        _grouped_bars(ax, groups, series, "good picks per hour")
        save(fig, "picks_per_hour.png", "Picks per hour")

    if not written:
        raise BinpickError(
            f"{folder}: no figure the report plots (precision, recall, cycle_s, *_s_median, picks_per_hour)"
        )
    _write_pages(out, written, machines, sorted({f.bench for f in figures}))
    return [p for p, _ in written]


def _write_pages(out: Path, written: list[tuple[Path, str]], machines: dict[str, dict], benches: list[str]) -> None:
    from binpick.io.atomic import write_text

    machine_rows = "".join(
        f"<tr><td>{html.escape(b)}</td><td>{html.escape(str(m.get('cpu_model')))}</td>"
        f"<td>{m.get('cores_usable')}</td><td>{html.escape(str(m.get('cuda') or 'none'))}</td></tr>"
        for b, m in machines.items()
    )
    sections = "".join(
        f'<h2>{html.escape(title)}</h2><img src="{p.name}" alt="{html.escape(title)}">' for p, title in written
    )
    write_text(
        out / "index.html",
        "<!doctype html><html lang='en'><head><meta charset='utf-8'><title>binpick benchmarks</title>"
        "<style>body{font-family:system-ui,sans-serif;margin:1.5em}img{max-width:100%}td,th{border:1px solid #ccc;"
        "padding:.2em .5em}table{border-collapse:collapse}</style></head><body><h1>Benchmarks</h1>"
        f"<p>From {', '.join(html.escape(b) for b in benches)}.</p>"
        f"<table><tr><th>file</th><th>CPU</th><th>cores</th><th>GPU</th></tr>{machine_rows}</table>"
        f"{sections}</body></html>\n",
    )
    md = [f"From {', '.join(f'`{b}.json`' for b in benches)}.", ""]
    md += ["| file | CPU | cores | GPU |", "|---|---|---|---|"]
    md += [
        f"| {b} | {m.get('cpu_model')} | {m.get('cores_usable')} | {m.get('cuda') or 'none'} |"
        for b, m in machines.items()
    ]
    for p, title in written:
        md += ["", f"### {title}", "", f"![{title}]({p.name})"]
    write_text(out / "plots.md", "\n".join(md) + "\n")
