"""Bin-clearing benchmark: bins of a part settled by the physics mode, emptied one pick at a time
through the real scene path, every pick checked against the simulator's true state.

Per bin: 10-20 parts dropped and settled (pybullet). Then, until the bin is empty or 3 picks in a
row failed: render what the camera sees (the project's camera, full resolution, sensor noise),
write it as a Zivid SDK 1.x file, read it back and run import, segmentation (when the part has a
trained network), registration and picks in process; take the first pick and check it:
- it touches a real part: suction: the cup's contact within TOUCH_M of a true part's surface
  (plus half the travel of a bellows cup, pick.suction.stroke_m: its lip, half pressed at the
  contact, meets a surface that much nearer or farther), its approach within TOUCH_DEG of that
  surface's inward normal under the cup (TrueSurface);
  jaws: both contacts within TOUCH_M of the same true part's surface;
- its path is free: the gripper swept along the approach reaches no deeper than PENETRATION_M
  into the true meshes of the other parts or the bin (nor deeper into its target than the contact
  may lie off it).
A good pick removes that part and the rest settle again; a failed one is counted and the bin is
captured again (new sensor noise). Keys per part: pick_success_rate (good picks / attempts),
clearance_rate (parts removed / parts settled in the bins), wrong_part_picks (picks that touch no
part), collisions (picks on a part whose path hits something), cycle_s_median (reading the
capture file to the ordered picks, on this machine), n_bins, n_attempts; besides them
attempts_without_a_pick (captures where no part had a reachable, collision-free grasp: failures)
and executed_pick_success_rate (good picks / picks made). Each bin is seen by a camera tilted from
the bin's up axis, the tilts spread evenly over 0 to tilt_deg_max (45 by default) across a part's
bins, each about its own horizontal axis; `by_tilt` gives the keys over all parts per band of tilt.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from binpick.cell.robot import MAX_FAILURES_IN_A_ROW
from binpick.errors import BinpickError
from binpick.generation.bin import bin_meshes
from binpick.generation.physics import SettleSettings, settle
from binpick.generation.placement import place_objects
from binpick.generation.scene import render_scene, settle_in_bin, tilted_camera
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.part_model import PartModel
from binpick.io.zdf import save_zdf_v1
from binpick.layout import Layout
from binpick.params import BinParams, Params, PickParams
from binpick.part.model import density_kg_m3
from binpick.picking.grasps import REVOLUTION_GRASP_STEPS, expand_by_symmetry, generate_grasps, patch_surface
from binpick.picking.gripper import gripper_primitives, signed_distance, swept, translated_poses
from binpick.picking.obstacles import TOOL_STEP_M
from binpick.registration.model import train_ppf
from binpick.scene.process import PartModels, chosen_verification, process
from binpick.scene.register import with_verification
from binpick.seeding import SceneSeeds, derive_seed
from binpick.view import ViewParams
from flows.bench import BENCH_PARTS, machine
from flows.bench.clutter import TILT_DEG_MAX, per_band, scaled_settings, tilt_band

log = logging.getLogger(__name__)

DEFAULT_PARTS = BENCH_PARTS
TOUCH_M = 0.002
TOUCH_DEG = 10.0
PENETRATION_M = 0.0005
BIN_SAMPLE_SPACING_M = 0.002


@dataclass
class Tally:
    """Attempts and what came of them; missed: first picks that touch no part as a grasp should
    (the key wrong_part_picks of a one-part bin); other_part: a mixed bin's first picks that touch
    an instance of another part than the one they name."""

    attempts: int = 0
    good: int = 0
    missed: int = 0
    other_part: int = 0
    collisions: int = 0
    no_pick: int = 0
    settled: int = 0
    removed: int = 0
    lost: int = 0

    def add(self, other: Tally) -> None:
        for k in vars(self):
            setattr(self, k, getattr(self, k) + getattr(other, k))


# Random drops tried per part, the lowest kept. The training scenes' 8 leave gaps that a long or
# bulky part fits in unfound: the ring screw's bin (0.34 x 0.25 m) held 9-14 of 20, the gear
# shaft's 12-19; with 32 it holds 14-16 and 20 (6 bins each), so that every bin of 10-20 parts
# asked for gets 10 or more.
DROPS_PER_PART = 32


def picking_settings(settings: Params, part: PartModel) -> Params:
    """The clutter benchmark's bin, camera and grids for the part's size, without distractors
    or tilt (a plain bin of one part), the physics mode, and room for 10-20 parts."""
    p = scaled_settings(settings, part)
    g = p.generate
    generate = g.model_copy(
        update={
            "clutter": g.clutter.off(),
            "placement": g.placement.model_copy(
                update={
                    "mode": "physics",
                    "candidates_per_object": max(g.placement.candidates_per_object, DROPS_PER_PART),
                    "max_pile_height_m": max(g.placement.max_pile_height_m, 0.6 * part.diameter_m),
                }
            ),
        }
    )
    return p.model_copy(update={"generate": generate, "camera": p.camera.model_copy(update={"downscale": 1})})


def touch_m(pick: PickParams, kind: str) -> float:
    """How far from a true surface the judge takes a gripper's contact to touch it: TOUCH_M, plus
    half a bellows suction cup's travel."""
    return TOUCH_M + (pick.suction.stroke_m / 2.0 if kind == "suction" else 0.0)


def bench_models(part: PartModel, p: Params, checkpoint: Path | None) -> PartModels:
    """The part's models built in memory for a benchmark: its PPF model, its network when the
    checkpoint exists (else registration over the whole scene) and its grasps for p.pick.gripper."""
    ppf = train_ppf(part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), p.registration)
    segmenter = None
    if checkpoint is not None and checkpoint.is_file():
        from binpick.network.infer import load_segmenter

        segmenter = load_segmenter(checkpoint, p.segment)
    mode = p.registration.mode if segmenter is not None else "whole_scene"
    kind = p.pick.gripper
    grasps = expand_by_symmetry(
        generate_grasps(part, p.pick)[kind], symmetry_transforms(part.symmetry, REVOLUTION_GRASP_STEPS)
    )
    return PartModels(
        part,
        ppf,
        segmenter,
        p.import_capture,
        with_verification(
            p.registration.model_copy(update={"mode": mode}),
            chosen_verification(checkpoint and Layout.verification_of(checkpoint), segmenter),
        ),
        grasps,
        p.pick,
        density_kg_m3=density_kg_m3(p, part.name),
    )


class TrueSurface:
    """The part's true mesh as the judge reads it (model frame): the closest point to a contact,
    and the surface's inward normal under a suction cup there: the mean normal of an even,
    dense sample of the mesh within the cup's radius (the faces facing the cup). On a flat face
    that is the face's normal; on a coarsely faceted curve (the gear shaft's STL turns by up to
    15 degrees within one facet) it is the curved surface's, not one facet's, which a pose that
    leaves the part's turn about its axis open would meet anywhere across. The sample is the one
    the suction grasps read their patches from (grasping.patch_surface). Built once per part."""

    def __init__(self, part: PartModel, cup_radius_m: float, touch_m: float = TOUCH_M) -> None:
        self.mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
        self.query = trimesh.proximity.ProximityQuery(self.mesh)
        self.points_m, self.normals = patch_surface(part, cup_radius_m)
        self.tree = cKDTree(self.points_m)
        self.cup_radius_m = cup_radius_m
        self.touch_m = touch_m

    def approach_off_deg(
        self, closest_m: np.ndarray, face: int, T_cam_from_object: np.ndarray, T_cam_from_tool: np.ndarray
    ) -> float:
        """Degrees between the tool's approach and the inward normal under a cup at closest_m (3,),
        model frame (on `face`): the mean over the sample within the cup's radius facing the
        cup, else the face's own."""
        approach = T_cam_from_object[:3, :3].T @ T_cam_from_tool[:3, 2]
        near = np.asarray(self.tree.query_ball_point(closest_m, self.cup_radius_m), dtype=np.int64)
        normals = self.normals[near]
        normals = normals[normals @ -approach > 0.0] if len(near) else normals
        mean = normals.sum(axis=0) if len(normals) else self.mesh.face_normals[face]
        return float(np.degrees(np.arccos(np.clip(-mean @ approach / np.linalg.norm(mean), -1, 1))))


def _true_touch(pick, kind: str, T_cam_from_objects: np.ndarray, truth: TrueSurface) -> int | None:
    """Index of the true object the pick touches as a grasp should, or None."""
    T = pick.T_cam_from_grasp
    if kind == "suction":
        contacts = T[:3, 3][None]
    else:
        half = T[:3, 0] * pick.width_m / 2.0
        contacts = np.stack([T[:3, 3] - half, T[:3, 3] + half])
    best = None
    for k, T_obj in enumerate(T_cam_from_objects):
        local = transform_points(invert_T(T_obj), contacts)
        closest, dist, tri = truth.query.on_surface(local)
        if np.any(dist > truth.touch_m):
            continue
        if kind == "suction" and truth.approach_off_deg(closest[0], int(tri[0]), T_obj, T) > TOUCH_DEG:
            continue
        if best is None or dist.max() < best[1]:
            best = (k, float(dist.max()))
    return None if best is None else best[0]


def _nearest_surface(
    T_cam_from_tool: np.ndarray, T_cam_from_objects: np.ndarray, truth: TrueSurface
) -> tuple[float, float]:
    """The distance (m) from the tool centre point to the nearest true part surface, and the angle
    (degrees) between the approach and that surface's inward normal under the cup: what a failed
    pick missed by."""
    best = (np.inf, 0.0)
    for T_obj in T_cam_from_objects:
        closest, dist, tri = truth.query.on_surface(transform_points(invert_T(T_obj), T_cam_from_tool[:3, 3][None]))
        if dist[0] < best[0]:
            best = (float(dist[0]), truth.approach_off_deg(closest[0], int(tri[0]), T_obj, T_cam_from_tool))
    return best


def _path_hits(
    pick,
    kind: str,
    params: Params,
    target: int,
    T_cam_from_objects: np.ndarray,
    object_points_m: np.ndarray | list[np.ndarray],
    bin_points_cam: np.ndarray,
) -> bool:
    """True when the swept gripper enters the true meshes of the others or the bin (or its target
    too deep), swept along its approach and, where the pick leaves another way (straight up), along
    that too. object_points_m: the objects' surface sample (m, 3), model frame: one for all (a
    bin of one part) or one per object (a mixed bin)."""
    tool = gripper_primitives(params.pick, kind, pick.width_m)
    body = swept(tool, max(params.pick.pregrasp_distance_m, params.pick.retreat_distance_m))
    placed = [(body, pick.T_cam_from_grasp, True)]
    out = pick.T_cam_from_postgrasp[:3, 3] - pick.T_cam_from_grasp[:3, 3]
    if np.linalg.norm(np.cross(out, pick.T_cam_from_grasp[:3, 2])) > 1e-6:
        # The target moves with the tool there: only the others and the bin are in its way.
        placed += [(tool, T, False) for T in translated_poses(pick.T_cam_from_grasp, out, TOOL_STEP_M)]
    target_depth_m = touch_m(params.pick, kind)
    for shape, T_cam_from_tool, with_target in placed:
        to_tool = invert_T(T_cam_from_tool)
        if (
            len(bin_points_cam)
            and signed_distance(transform_points(to_tool, bin_points_cam), shape).min() < -PENETRATION_M
        ):
            return True
        for k, T_obj in enumerate(T_cam_from_objects):
            if k == target and not with_target:
                continue
            points = object_points_m if isinstance(object_points_m, np.ndarray) else object_points_m[k]
            depth = signed_distance(transform_points(to_tool @ T_obj, points), shape).min()
            if depth < (-target_depth_m if k == target else -PENETRATION_M):
                return True
    return False


def bin_surface_points(bin_params: BinParams) -> np.ndarray:
    """(m, 3) an even sample of the bin's walls and floor, bin frame, BIN_SAMPLE_SPACING_M apart."""
    return np.concatenate(
        [
            trimesh.sample.sample_surface_even(m, int(m.area / BIN_SAMPLE_SPACING_M**2), seed=0)[0]
            for m in bin_meshes(bin_params)
        ]
    )


def draw_bin(
    bin_seed: np.random.SeedSequence,
    b: int,
    n_bins: int,
    parts_per_bin: tuple[int, int],
    tilt_deg_max: float,
    p: Params,
) -> tuple[int, float, np.ndarray]:
    """Bin b of n_bins: how many parts, the camera's tilt (degrees) and T_bin_from_camera. Tilts
    spread evenly over the range across the bins, each at a random heading."""
    draw = np.random.default_rng(bin_seed)
    n = int(draw.integers(parts_per_bin[0], parts_per_bin[1] + 1))
    tilt_deg = tilt_deg_max * (b + float(draw.uniform())) / n_bins
    T_bin_from_camera = tilted_camera(p.camera.distance_m, np.radians(tilt_deg), float(draw.uniform(0.0, 2.0 * np.pi)))
    return n, tilt_deg, T_bin_from_camera


def _clear_bin(
    part: PartModel,
    models: PartModels,
    p: Params,
    kind: str,
    n_parts: int,
    seed: np.random.SeedSequence,
    folder: Path,
    cycles: list[float],
    truth: TrueSurface,
    T_bin_from_camera: np.ndarray,
) -> Tally:
    rng = np.random.default_rng(seed)
    g = p.generate
    placed = place_objects(part.points_m, n_parts, g.bin, g.placement, rng)
    T_bin = settle_in_bin(part, placed.T_bin_from_model, g, rng)
    tally = Tally(settled=len(T_bin))
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(g.bin)]
    bin_points = bin_surface_points(g.bin)
    half = (g.bin.inner_x_m / 2.0, g.bin.inner_y_m / 2.0)
    view = ViewParams.of_import(p.import_capture)
    failures = 0
    capture = folder / "capture.zdf"
    while len(T_bin) and failures < MAX_FAILURES_IN_A_ROW:
        scene = render_scene(part, T_bin, g, p.camera, view, rng, T_bin_from_camera)
        H, W = scene.labels.shape
        save_zdf_v1(capture, scene.xyz_m * 1000.0)
        t0 = time.perf_counter()
        frame = load_capture(capture, ImportOptions("mm"))
        try:
            result = process(frame.xyz_m, frame.rgb, frame.shape, models, SceneSeeds.of(0, f"picking-{tally.attempts}"))
            plan = result.picks
        except BinpickError as exc:
            log.warning("%s: the scene path refused the capture: %s", part.name, exc)
            plan = None
        cycles.append(time.perf_counter() - t0)
        tally.attempts += 1
        T_cam = scene.T_cam_from_model
        if plan is None or not plan.picks:
            tally.no_pick += 1
            failures += 1
            log.info(
                "%s: no pick for %d parts left (%d poses; %s)",
                part.name,
                len(T_bin),
                len(plan.unpicked) if plan else 0,
                "; ".join(f"part {i}: {why}" for i, why in plan.unpicked) if plan else "refused",
            )
            continue
        first = plan.picks[0]
        target = _true_touch(first, kind, T_cam, truth)
        if target is None:
            tally.missed += 1
            failures += 1
            distance_m, angle_deg = _nearest_surface(first.T_cam_from_grasp, T_cam, truth)
            log.info(
                "%s: the first pick (part %d, grasp %s, pose score %.2f) touches no part as a grasp should: its "
                "contact lies %.1f mm from "
                "the nearest true surface, its approach %.0f degrees off that surface's inward normal",
                part.name,
                first.pose_index,
                first.grasp_id,
                first.score,
                1000 * distance_m,
                angle_deg,
            )
            continue
        if _path_hits(first, kind, p, target, T_cam, part.points_m, transform_points(scene.T_cam_from_bin, bin_points)):
            tally.collisions += 1
            failures += 1
            continue
        tally.good += 1
        tally.removed += 1
        failures = 0
        rest = np.delete(T_bin, target, axis=0)
        if len(rest):
            rest, inside = settle(
                part.mesh_vertices_m,
                part.mesh_faces,
                rest,
                boxes,
                SettleSettings(max_time_s=g.placement.settle_max_s, drop_gap_m=0.0),
                half,
            )
            tally.lost += int((~inside).sum())
            rest = rest[inside]
        T_bin = rest
    return tally


def bench_picking(
    settings: Params,
    names: list[str] | None,
    n_bins: int,
    parts_per_bin: tuple[int, int],
    checkpoints: dict[str, Path],
    gripper: str | None = None,
    seed: int = 0,
    tilt_deg_max: float = TILT_DEG_MAX,
    part_settings: dict[str, Params] | None = None,
) -> dict[str, object]:
    """settings: the project's params; checkpoints: part -> trained FPCC checkpoint (parts
    without one are registered over the whole scene); gripper: overrides pick.gripper;
    tilt_deg_max: the largest tilt of a bin's camera from the bin's up axis, degrees;
    part_settings: the params resolved for a part the project lists (its entry's overrides: its
    gripper), used for that part."""
    from flows.bench.parts import bench_parts

    parts = bench_parts(names, n_points=settings.ingest.n_surface_points)
    kind = gripper or settings.pick.gripper
    per_part: dict[str, dict[str, float | list[float]]] = {}
    out: dict[str, object] = {
        "machine": machine(),
        "gripper": kind,
        "parts_per_bin": list(parts_per_bin),
        "touch_m": TOUCH_M,
        "touch_deg": TOUCH_DEG,
        "penetration_m": PENETRATION_M,
        "tilt_deg_max": tilt_deg_max,
        "parts": per_part,
    }
    total = Tally()
    all_cycles: list[float] = []
    by_band: dict[str, list[tuple[Tally, list[float]]]] = {}  # band -> (tally, cycles) of each bin
    for part in parts:
        p = picking_settings((part_settings or {}).get(part.name, settings), part)
        kind = gripper or p.pick.gripper
        p = p.model_copy(update={"pick": p.pick.model_copy(update={"gripper": kind})})
        models = bench_models(part, p, checkpoints.get(part.name))
        assert models.grasps is not None
        grasps = models.grasps
        tally = Tally()
        cycles: list[float] = []
        truth = TrueSurface(part, p.pick.suction.cup_radius_m, touch_m(p.pick, kind))
        with tempfile.TemporaryDirectory(prefix="binpick-picking-") as tmp:
            for b in range(n_bins):
                bin_seed = derive_seed(seed, "bench-picking", part.name, b)
                n, tilt_deg, T_bin_from_camera = draw_bin(bin_seed, b, n_bins, parts_per_bin, tilt_deg_max, p)
                first_cycle = len(cycles)
                one = _clear_bin(part, models, p, kind, n, bin_seed, Path(tmp), cycles, truth, T_bin_from_camera)
                log.info(
                    "%s bin %d (camera tilted %.0f degrees): %d of %d removed in %d attempts (%d wrong part, %d "
                    "collisions, %d without a pick)",
                    part.name,
                    b,
                    tilt_deg,
                    one.removed,
                    one.settled,
                    one.attempts,
                    one.missed,
                    one.collisions,
                    one.no_pick,
                )
                tally.add(one)
                by_band.setdefault(tilt_band(tilt_deg), []).append((one, cycles[first_cycle:]))
        per_part[part.name] = {
            **_keys(tally, cycles, n_bins),
            "n_grasps": float(len(grasps)),
            "segmentation": 1.0 if models.segmenter is not None else 0.0,
            "diameter_mm": 1000.0 * part.diameter_m,
            "contact_touch_m": truth.touch_m,
        }
        total.add(tally)
        all_cycles += cycles
    out.update(_keys(total, all_cycles, n_bins * len(parts)))
    out["by_tilt"] = per_band(by_band, _band_keys)
    return out


def _band_keys(bins: list[tuple[Tally, list[float]]]) -> dict[str, float | list[float]]:
    """The keys over the bins of one band of tilt."""
    total = Tally()
    for one, _ in bins:
        total.add(one)
    return _keys(total, [c for _, cycles in bins for c in cycles], len(bins))


def _keys(t: Tally, cycles: list[float], n_bins: int) -> dict[str, float | list[float]]:
    return {
        "pick_success_rate": t.good / t.attempts if t.attempts else 0.0,
        "clearance_rate": t.removed / t.settled if t.settled else 0.0,
        "wrong_part_picks": float(t.missed),
        "collisions": float(t.collisions),
        "cycle_s_median": float(np.median(cycles)) if cycles else 0.0,
        "cycle_s": [round(float(c), 4) for c in cycles],  # each cycle, for `binpick bench report`
        "n_bins": float(n_bins),
        "n_attempts": float(t.attempts),
        "attempts_without_a_pick": float(t.no_pick),
        # Of the picks the pipeline made (attempts without a pick are failures above, not here).
        "executed_pick_success_rate": t.good / (t.attempts - t.no_pick) if t.attempts > t.no_pick else 0.0,
        "parts_settled": float(t.settled),
        "parts_lost_by_physics": float(t.lost),
    }
