"""Ingest benchmark: CAD meshes of 10^4 to 2 x 10^6 faces through the real ingest kernel, each in
a fresh process so that its peak memory is its own.

The meshes have a known diameter: UV spheres (their poles are antipodal vertices, so the
diameter is exactly 2 r) and the built-in T-joint subdivided (subdivision keeps the surface, so
the diameter is the one of the original, computed exactly over its convex hull).
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from binpick.params import Params
from flows.bench import machine

SPHERE_RADIUS_MM = 30.0
SPHERE_FACES = (10_000, 100_000, 1_000_000, 2_000_000)
T_JOINT_SUBDIVISIONS = (2, 4, 5)  # 772 faces x 4^k: 12 k, 198 k, 791 k


def _sphere(n_faces: int) -> trimesh.Trimesh:
    side = int(round(np.sqrt(n_faces / 4.0)))  # a count x count UV sphere has about 4 count^2 faces
    return trimesh.creation.uv_sphere(radius=SPHERE_RADIUS_MM, count=[side, side])


def bench_meshes() -> list[tuple[str, trimesh.Trimesh, float]]:
    """(name, mesh in millimetres, true diameter in mm) for every benchmarked size."""
    from binpick.part.model import build_t_joint_mesh, diameter

    out = [(f"sphere_{n}", _sphere(n), 2.0 * SPHERE_RADIUS_MM) for n in SPHERE_FACES]
    base = build_t_joint_mesh()
    truth = diameter(base.vertices)  # exact: the hull of 772 faces is small
    for k in T_JOINT_SUBDIVISIONS:
        vertices, faces = base.vertices, base.faces
        for _ in range(k):
            vertices, faces = trimesh.remesh.subdivide(vertices, faces)
        out.append((f"t_joint_subdivided_{k}", trimesh.Trimesh(vertices, faces, process=False), truth))
    return out


def _child(params: Params, mesh_path: str, queue: Any) -> None:
    """Ingest one mesh in this (fresh) process; report time, peak memory and the diameter."""
    from binpick.errors import BinpickError
    from binpick.part.ingest import ingest_part

    t0 = time.perf_counter()
    result: dict[str, Any]
    try:
        model, metrics = ingest_part(params, "bench", Path(mesh_path))
        result = {
            "ingest_s": time.perf_counter() - t0,
            "diameter_mm": 1000.0 * model.diameter_m,
            "n_faces_model": int(len(model.mesh_faces)),
        }
    except BinpickError as exc:
        result = {"error": str(exc)}
    result["peak_rss_mb"] = _peak_rss_mb()
    queue.put(result)


def _peak_rss_mb() -> float:
    """This process's own peak resident memory. Not getrusage's ru_maxrss, which Linux carries
    over from the parent across fork and exec (a spawned child would report the parent's peak)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_ingest(settings: Params) -> dict[str, object]:
    """settings: the project's params; the meshes are ingested as a part in millimetres."""
    from binpick.params import PartParams

    params = settings.model_copy(update={"parts": {"bench": PartParams(mesh="bench.stl", unit="mm")}})
    ctx = mp.get_context("spawn")  # a fresh interpreter: peak memory of this mesh only
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, mesh, truth_mm in bench_meshes():
            path = Path(tmp) / f"{name}.stl"
            mesh.export(path)
            n_faces = int(len(mesh.faces))
            del mesh
            queue = ctx.Queue()
            proc = ctx.Process(target=_child, args=(params, str(path), queue))
            proc.start()
            got = queue.get()
            proc.join()
            path.unlink()
            row: dict[str, Any] = {"n_faces": n_faces, "peak_rss_mb": round(got["peak_rss_mb"], 1)}
            if "error" in got:
                row["error"] = got["error"]
            else:
                row.update(
                    ingest_s=round(got["ingest_s"], 3),
                    n_faces_model=got["n_faces_model"],
                    diameter_rel_error=abs(got["diameter_mm"] - truth_mm) / truth_mm,
                )
            results[name] = row
    ok = [r for r in results.values() if "error" not in r]
    largest = max(ok, key=lambda r: r["n_faces"]) if ok else {}
    return {
        "machine": machine(),
        "meshes": results,
        "max_ingest_s": max((r["ingest_s"] for r in ok), default=None),
        "max_peak_rss_mb": max((r["peak_rss_mb"] for r in ok), default=None),
        "max_diameter_rel_error": max((r["diameter_rel_error"] for r in ok), default=None),
        "largest_n_faces": largest.get("n_faces"),
        "targets": {"ingest_s_2m_faces": 60.0, "peak_rss_mb": 4096.0, "diameter_rel_error": 1e-3},
    }
