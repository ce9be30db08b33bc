"""PPF registration benchmark: this matcher against OpenCV's PPF3DDetector + ICP and Open3D's
FPFH + RANSAC + ICP, on the same rendered views (1 mm noise, 10% clutter) in one run."""

from __future__ import annotations

import logging
import time

import numpy as np
import open3d as o3d

from binpick.generation.camera import camera_of, render
from binpick.geometry.camera import PinholeCamera
from binpick.geometry.pointcloud import estimate_normals, voxel_downsample_indices
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import make_T, random_rotation, transform_points
from binpick.io.part_model import PartModel
from binpick.metrics.pose import pose_errors
from binpick.params import Params, RegisterParams
from binpick.registration.matching import match_segment
from binpick.registration.model import train_ppf
from flows.bench import machine
from flows.bench.parts import bench_parts

log = logging.getLogger(__name__)

NOISE_M = 0.001
CLUTTER_FRACTION = 0.10


def make_view(
    part: PartModel, rng: np.random.Generator, intr: PinholeCamera
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A view of the part alone at a random pose: (points (n, 3), normals, T_cam_from_model).

    The part is rendered from the virtual camera, sampled on the pipeline's 2 mm grid (1/100 of
    the diameter for large parts),
    given isotropic Gaussian noise of NOISE_M and CLUTTER_FRACTION extra random points in its
    box; normals are estimated as the pipeline does."""
    d = part.diameter_m
    R = random_rotation(rng)
    centre = part.centre_m
    t = np.array([rng.uniform(-0.1, 0.1) * d, rng.uniform(-0.1, 0.1) * d, 0.3 + 1.5 * d]) - R @ centre
    T = make_T(R, t)
    r = render([(transform_points(T, part.mesh_vertices_m), part.mesh_faces)], [0], intr)
    pts = r.xyz_m.reshape(-1, 3)[r.labels.reshape(-1) == 0].astype(np.float64)
    pts = pts[voxel_downsample_indices(pts, max(0.002, d / 100))]
    pts = pts + rng.normal(0, NOISE_M, pts.shape)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.1 * (hi - lo)
    clutter = rng.uniform(lo - pad, hi + pad, (int(CLUTTER_FRACTION * len(pts)), 3))
    pts = np.vstack([pts, clutter])
    normals = estimate_normals(pts, max(0.004, 0.04 * d))
    return pts, normals.astype(np.float64), T


def _ours(part: PartModel, params: RegisterParams):
    t0 = time.perf_counter()
    model = train_ppf(part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), params)
    train_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)

    def match(pts, nrm):
        est = match_segment(model, pts, nrm, params, rng)
        return None if est is None else est.T_cam_from_model

    return train_s, match


def _opencv(part: PartModel, params: RegisterParams):
    import cv2

    # OpenCV samples the model itself, but its training cost grows fast with the input: give it
    # the model on its own sampling grid.
    idx = voxel_downsample_indices(part.points_m, params.sample_step_rel * part.diameter_m)
    model_pc = np.hstack([part.points_m[idx], part.normals[idx]]).astype(np.float32)
    t0 = time.perf_counter()
    detector = cv2.ppf_match_3d_PPF3DDetector(  # type: ignore[attr-defined]  # opencv-contrib, not in cv2's stubs
        params.sample_step_rel, params.distance_step_rel
    )
    detector.trainModel(model_pc)
    train_s = time.perf_counter() - t0
    icp = cv2.ppf_match_3d_ICP(100, 0.005, 2.5, 8)  # type: ignore[attr-defined]

    def match(pts, nrm):
        scene_pc = np.hstack([pts, nrm]).astype(np.float32)
        results = detector.match(scene_pc, params.scene_ref_fraction, params.distance_step_rel)
        if not results:
            return None
        _, refined = icp.registerModelToScene(model_pc, scene_pc, results[:5])
        return np.asarray(refined[0].pose, dtype=np.float64)

    return train_s, match


def _open3d(part: PartModel, params: RegisterParams):
    voxel = params.sample_step_rel * part.diameter_m
    reg = o3d.pipelines.registration
    t0 = time.perf_counter()
    idx = voxel_downsample_indices(part.points_m, voxel)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(part.points_m[idx].astype(np.float64)))
    src.normals = o3d.utility.Vector3dVector(part.normals[idx].astype(np.float64))
    feature = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    src_fpfh = reg.compute_fpfh_feature(src, feature)  # type: ignore[call-arg]  # indices is optional at run time
    train_s = time.perf_counter() - t0
    dense = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(part.points_m.astype(np.float64)))
    dense.normals = o3d.utility.Vector3dVector(part.normals.astype(np.float64))
    o3d.utility.random.seed(0)

    def match(pts, nrm):
        k = voxel_downsample_indices(pts, voxel)
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[k]))
        tgt.normals = o3d.utility.Vector3dVector(nrm[k])
        tgt_fpfh = reg.compute_fpfh_feature(tgt, feature)  # type: ignore[call-arg]  # open3d 0.20 stubs name an `indices` its binding does not need
        ransac = reg.registration_ransac_based_on_feature_matching(
            src,
            tgt,
            src_fpfh,
            tgt_fpfh,
            True,
            1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999),
        )
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        scene.normals = o3d.utility.Vector3dVector(nrm)
        icp = reg.registration_icp(
            dense, scene, 0.5 * voxel, ransac.transformation, reg.TransformationEstimationPointToPlane()
        )
        return np.asarray(icp.transformation)

    return train_s, match


METHODS = {"binpick_ppf": _ours, "opencv_ppf_icp": _opencv, "open3d_fpfh_ransac_icp": _open3d}


def _summarise(rows: list[dict[str, float]], train_s: list[float]) -> dict[str, float]:
    ms = np.array([r["ms"] for r in rows])
    ok = [r for r in rows if r.get("rot_err_deg") is not None]

    def med(k):
        return float(np.median([r[k] for r in ok])) if ok else float("nan")

    return {
        "n_trials": float(len(rows)),
        "ms_per_instance_median": float(np.median(ms)),
        "ms_per_instance_p90": float(np.percentile(ms, 90)),
        "add_success_rate": float(np.mean([r.get("add_ok", 0.0) for r in rows])),
        "success_rate_5deg_5mm": float(np.mean([r.get("ok_5deg_5mm", 0.0) for r in rows])),
        "rot_err_deg_median": med("rot_err_deg"),
        "trans_err_mm_median": med("trans_err_mm"),
        "train_s": float(np.median(train_s)),
        "train_s_max": float(np.max(train_s)),
    }


def bench_ppf(
    settings: Params, parts: list[str] | None = None, trials: int = 20, methods: list[str] | None = None, seed: int = 0
) -> dict[str, object]:
    """settings: the project's params (the register section and the camera are used)."""
    methods = methods or list(METHODS)
    params = settings.registration
    intr = camera_of(settings.camera.model_copy(update={"downscale": 2}))
    models = bench_parts(parts)
    per_method: dict[str, list[dict[str, float]]] = {m: [] for m in methods}
    per_part: dict[str, dict[str, dict[str, float]]] = {}
    train_times: dict[str, list[float]] = {m: [] for m in methods}
    for part in models:
        syms = symmetry_transforms(part.symmetry)
        rng = np.random.default_rng([seed, len(part.name)])
        views = [make_view(part, rng, intr) for _ in range(trials)]
        per_part[part.name] = {}
        for name in methods:
            train_s, match = METHODS[name](part, params)
            train_times[name].append(train_s)
            rows = []
            for pts, nrm, T_gt in views:
                t0 = time.perf_counter()
                T = match(pts, nrm)
                row = {"ms": 1000.0 * (time.perf_counter() - t0)}
                if T is not None:
                    row.update(pose_errors(T, T_gt, part.points_m, syms, part.diameter_m))
                rows.append(row)
            per_method[name] += rows
            per_part[part.name][name] = _summarise(rows, [train_s])
            log.info("%s / %s: %s", part.name, name, {k: round(v, 3) for k, v in per_part[part.name][name].items()})
    result: dict[str, object] = {m: _summarise(per_method[m], train_times[m]) for m in methods}
    result["per_part"] = per_part
    result["setup"] = {
        "parts": [p.name for p in models],
        "trials_per_part": trials,
        "noise_mm": 1000 * NOISE_M,
        "clutter_fraction": CLUTTER_FRACTION,
        "machine": machine(),
    }
    if "binpick_ppf" in methods and "opencv_ppf_icp" in methods:
        ours, theirs = result["binpick_ppf"], result["opencv_ppf_icp"]
        result["speedup_vs_opencv"] = theirs["ms_per_instance_median"] / ours["ms_per_instance_median"]  # type: ignore[index]
    return result
