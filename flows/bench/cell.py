"""The cell benchmark: bins emptied by the simulated arm (binpick/cell/simulation.py), every pick
executed in physics, the cell judged as its owner would: picks per hour with no failed or
colliding pick.

Per part: bins of 10-20 parts settled as in `bench picking` (a plain bin, the camera straight above
it); the arm (cell.arm) stands beside the bin's long side with its base at the floor's height, the
place is a drop zone beside the bin's short side, level with its middle (cell.place's kind and
tolerances). Until the bin is empty or 3 attempts in a row fail (a part the gripper failed to hold
is left alone until nothing else can be picked, as in `binpick cell run`): render what the camera
sees, run the real scene path in
process (import, segmentation when the part has a trained network, registration, picks with the
arm's check) and execute the first pick in physics from where the arm is. A pick is good when the
part arrives at the place within tolerance, nothing else left the bin with it and neither the arm
nor the tool touched anything but the target on the way.

Time: each attempt's motion is the simulated arm's (ruckig at the rated joint limits times
cell.speed_scaling, plus the cup's dwell); the next capture is taken once the arm has left the
camera's view after its grasp, so perception and planning overlap the rest of the motion and only
what does not fit is added (the first capture of a bin waits for nothing). picks_per_hour = good
picks / that wall time. cycle_s_median: perception plus arm planning of one capture on this machine.

`baseline_*`: the same bins with today's gripper-only picks: the first pick's tool pose handed to
the arm as is (no turn about the cup's axis, the controller's nearest IK solution, no margins, no
check of the arm's path), executed the same way; `baseline_failures` names its failures by cause.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from binpick.cell.retries import FailedGrips
from binpick.cell.robot import GRASP_LOST, MAX_FAILURES_IN_A_ROW, NO_GRIP, PICKS_PER_CAPTURE, Execution
from binpick.cell.simulation import SimulatedCell
from binpick.errors import BinpickError
from binpick.generation.bin import T_bin_from_cam, bin_meshes
from binpick.generation.camera import camera_of
from binpick.generation.placement import place_objects
from binpick.generation.scene import render_scene, settle_in_bin
from binpick.geometry.camera import in_view_of
from binpick.geometry.transforms import invert_T, make_T
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.part_model import PartModel
from binpick.io.zdf import save_zdf_v1
from binpick.params import CellParams, Params
from binpick.part.model import density_kg_m3 as part_density
from binpick.part.model import part_mass_kg
from binpick.picking.arm import ArmMotion, ArmPlanner
from binpick.picking.gripper import holding_force_n
from binpick.registration.visibility import DepthView
from binpick.robot.arm import load_arm
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds, derive_seed
from binpick.view import ViewParams
from flows.bench import BENCH_PARTS, machine
from flows.bench.cell_recording import CellRecording
from flows.bench.picking import bench_models, picking_settings

log = logging.getLogger(__name__)

DEFAULT_PARTS = BENCH_PARTS
# The arm's base stands this far out from the bin's outer long wall; the drop zone this far out
# from its short wall, this high above the wall's top.
BASE_GAP_M, PLACE_GAP_M, PLACE_HEIGHT_M = 0.15, 0.2, 0.05
# The home: the tool straight down this high above the wall's top over the bin's centre.
HOME_HEIGHT_M = 0.25
# Where the search for the home starts (a UR's elbow-up pose).
ELBOW_UP = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


@dataclass
class Tally:
    attempts: int = 0
    executed: int = 0
    good: int = 0
    collisions: int = 0
    dropped: int = 0
    double: int = 0
    unreachable_sent: int = 0
    settled: int = 0
    removed: int = 0
    lost: int = 0  # parts that left the bin otherwise (with a pick, or thrown out)
    wall_s: float = 0.0
    motion_s: list[float] = field(default_factory=list)
    failures: Counter[str] = field(default_factory=Counter)

    def add(self, other: Tally) -> None:
        for k, v in vars(other).items():
            mine = getattr(self, k)
            if isinstance(v, Counter):
                mine.update(v)
            elif isinstance(v, list):
                mine.extend(v)
            else:
                setattr(self, k, mine + v)


@dataclass(frozen=True)
class CellLayout:
    """Where the arm, the camera and the place are for a bin: T_bin_from_base, T_base_from_cam,
    the cell settings with the place and the home for this bin."""

    T_bin_from_base: np.ndarray
    T_base_from_cam: np.ndarray
    T_bin_from_camera: np.ndarray
    cell: CellParams


def cell_layout(p: Params) -> CellLayout:
    """The arm beside the bin's long side (base x toward the bin) on a pedestal level with the
    bin's rim, the camera straight above the floor's centre, a drop zone beside the bin's short
    side, level with its middle."""
    b = p.generate.bin
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # base x along the bin's y
    # Level with the rim, as cells mount an arm over a deep bin: on the floor beside the gear
    # shaft's 0.2 m walls the UR10's upper arm met the near wall in every plan into the bin.
    T_bin_from_base = make_T(
        R, np.array([0.0, -(b.inner_y_m / 2.0 + b.wall_thickness_m + BASE_GAP_M), b.wall_height_m])
    )
    T_base_from_bin = invert_T(T_bin_from_base)
    T_bin_from_camera = T_bin_from_cam(p.camera.distance_m)
    # Level with the bin's middle, as a cell is laid out for a short swing: in a 0.3 x 0.2 m bin
    # the base turns 11 to 97 degrees from a part to the place (level with the base: 47 to 133).
    place_bin = np.array(
        [-(b.inner_x_m / 2.0 + b.wall_thickness_m + PLACE_GAP_M), 0.0, b.wall_height_m + PLACE_HEIGHT_M]
    )
    place = p.cell.place.model_copy(
        update={
            "kind": "drop",
            "T_base_from_part": make_T(
                np.eye(3), T_base_from_bin[:3, :3] @ place_bin + T_base_from_bin[:3, 3]
            ).tolist(),
        }
    )
    arm = load_arm(p.cell.arm or "ur5e")
    over = make_T(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, b.wall_height_m + HOME_HEIGHT_M]))
    flange = T_base_from_bin @ over @ invert_T(np.asarray(p.cell.T_flange_from_tcp, dtype=float))
    solutions = arm.ik(flange)
    if len(solutions) == 0:
        raise ValueError(f"{arm.name}: the bin's centre ({T_base_from_bin[0, 3]:.2f} m away) is out of reach")
    home = solutions[np.argmin(np.abs(np.angle(np.exp(1j * (solutions - ELBOW_UP)))).sum(axis=1))]
    # The table under the pedestal and the bin is the bin's ground (its floor's top).
    cell = p.cell.model_copy(
        update={"place": place, "home_q_rad": [float(x) for x in home], "table_z_m": -b.wall_height_m}
    )
    return CellLayout(T_bin_from_base, T_base_from_bin @ T_bin_from_camera, T_bin_from_camera, cell)


def _clear_bin(
    part: PartModel,
    models: PartModels,
    p: Params,
    layout: CellLayout,
    baseline: ArmPlanner | None,
    n_parts: int,
    seed: np.random.SeedSequence,
    folder: Path,
    cycles: list[float],
    density_kg_m3: float,
    record: Path | None = None,
) -> Tally:
    """One bin emptied; record: a rerun recording of it written there."""
    rng = np.random.default_rng(seed)
    g = p.generate
    placed = place_objects(part.points_m, n_parts, g.bin, g.placement, rng)
    T_bin = settle_in_bin(part, placed.T_bin_from_model, g, rng)
    tally = Tally(settled=len(T_bin))
    in_view = in_view_of(camera_of(p.camera), invert_T(layout.T_bin_from_camera))

    arm = load_arm(layout.cell.arm or "ur5e")
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(g.bin)]
    sim = SimulatedCell(
        arm,
        layout.cell,
        p.pick,
        p.pick.gripper,
        part,
        density_kg_m3,
        boxes,
        (g.bin.inner_x_m / 2.0, g.bin.inner_y_m / 2.0),
        layout.T_bin_from_base,
        T_bin,
        in_view,
    )
    recording = (
        CellRecording(record, part.name, arm, layout.T_bin_from_base, np.asarray(layout.cell.T_flange_from_tcp), boxes)
        if record is not None
        else None
    )
    view = ViewParams.of_import(p.import_capture)
    capture = folder / "capture.zdf"
    q = np.asarray(layout.cell.home_q_rad, dtype=float)
    hidden_s = 0.0  # perception that fits in the previous motion after the arm left the view
    failures = 0
    failed_grips = FailedGrips()  # parts left alone until nothing else is left, as in binpick cell run
    try:
        while failures < MAX_FAILURES_IN_A_ROW:
            inside = sim.in_bin()
            poses, index = sim.part_poses()
            keep = [k for k, i in enumerate(index) if inside[i]]
            if not keep:
                break
            scene = render_scene(part, poses[keep], g, p.camera, view, rng, layout.T_bin_from_camera)
            save_zdf_v1(capture, scene.xyz_m * 1000.0)
            t0 = time.perf_counter()
            frame = load_capture(capture, ImportOptions("mm"))
            try:
                result = process(
                    frame.xyz_m,
                    frame.rgb,
                    frame.shape,
                    models,
                    SceneSeeds.of(0, f"cell-{tally.attempts}"),
                    q,
                    PICKS_PER_CAPTURE,
                    failed_grips,
                )
                plan = result.picks
            except BinpickError as exc:
                log.warning("%s: the scene path refused the capture: %s", part.name, exc)
                plan = None
            perception_s = time.perf_counter() - t0
            cycles.append(perception_s)
            tally.attempts += 1
            tally.wall_s += max(0.0, perception_s - hidden_s)
            hidden_s = 0.0
            if plan is not None and not plan.picks and failed_grips.retry():
                continue  # no other pick: the parts the gripper failed to hold are tried again
            if plan is None or not plan.picks:
                failures += 1
                why = Counter(_leading_cause(reason) for _, reason in plan.unpicked) if plan is not None else None
                tally.failures[f"no pick ({why.most_common(1)[0][0]})" if why else "no pick"] += 1
                if recording is not None:
                    recording.attempt(tally.attempts, part, poses[keep], None, "no pick")
                continue
            first = plan.picks[0]
            if baseline is None:
                motion: ArmMotion | str = first.arm if first.arm is not None else "no arm plan"
            else:
                T_model_from_tool = models.grasps.T_model_from_tool[first.grasp_index]  # type: ignore[union-attr]
                motion = baseline.plan(
                    first.T_cam_from_grasp,
                    T_model_from_tool,
                    p.pick.gripper,
                    part.centre_m,
                    q,
                    retreat_cam=first.retreat_cam,
                )
            if isinstance(motion, str):
                # A plan the robot cannot execute: the controller refuses it, the cell stops.
                tally.unreachable_sent += 1
                tally.failures[motion] += 1
                failures += 1
                if recording is not None:
                    recording.attempt(tally.attempts, part, poses[keep], None, f"plan not executable: {motion}")
                continue
            done = sim.execute(motion, q, first.width_m)
            tally.executed += 1
            tally.wall_s += done.motion_s
            tally.motion_s.append(done.motion_s)
            hidden_s = max(0.0, done.motion_s - done.out_of_view_s)
            log.debug(
                "%s attempt %d: perception %.2f s, motion %.2f s (out of view from %.2f s), carry at %.2f of the speed",
                part.name,
                tally.attempts,
                perception_s,
                done.motion_s,
                done.out_of_view_s,
                motion.carry_share,
            )
            q = sim.joints()
            good = _judge(done, tally)
            if recording is not None:
                touched = f", touched {' and '.join(sorted(done.touched))}" if done.touched else ""
                recording.attempt(tally.attempts, part, poses[keep], motion, f"{done.outcome}{touched}")
            if done.state in (NO_GRIP, GRASP_LOST):  # what the vacuum sensor or the jaws tell, as in cell run
                failed_grips.failed(
                    result.registration.poses[first.pose_index].T_cam_from_model,
                    part.centre_m,
                    first.T_cam_from_grasp,
                    held=done.state == GRASP_LOST,
                )
            tally.removed += int(done.outcome in ("placed", "misplaced"))
            tally.lost += sim.remove_outside()
            failures = 0 if good else failures + 1
    finally:
        sim.close()
        if recording is not None:
            recording.close()
    return tally


def _leading_cause(reason: str) -> str:
    """An unpicked part's reason cut to its kind and its commonest cause ('no grasp in reach the arm
    can execute: too heavy for the gripper (12), unreachable (2)' -> '...: too heavy for the
    gripper'), so that the tally's keys say what stopped the picks without their counts."""
    head, _, causes = reason.partition(": ")
    first = re.sub(r" \(\d+\)$", "", causes.split(", ")[0].split("; ")[0]).removeprefix("with ")
    first = re.sub(r"part \d+$", "a detected part", first)  # which one differs from capture to capture
    return f"{head}: {first}" if first else head


def _judge(done: Execution, tally: Tally) -> bool:
    """Count what the execution did; whether it was a good pick."""
    if done.touched:
        tally.collisions += 1
        tally.failures["arm or tool touched " + " and ".join(sorted(done.touched))] += 1
    if done.outcome == "dropped":
        tally.dropped += 1
        tally.failures[f"dropped, {done.lost}" if done.lost else "dropped"] += 1
    if done.double:
        tally.double += 1
        tally.failures["another part came out with it"] += 1
    good = done.outcome == "placed" and not done.touched and not done.double
    if done.outcome not in ("placed", "dropped"):
        tally.failures[done.outcome] += 1
    elif good:
        tally.good += 1
    return good


def _keys(t: Tally, cycles: list[float], n_bins: int) -> dict[str, float | list[float]]:
    return {
        "executed_pick_success_rate": t.good / t.executed if t.executed else 0.0,
        "clearance_rate": t.removed / t.settled if t.settled else 0.0,
        "arm_collisions": float(t.collisions),
        "dropped_parts": float(t.dropped),
        "double_picks": float(t.double),
        "unreachable_plans_sent": float(t.unreachable_sent),
        "picks_per_hour": 3600.0 * t.good / t.wall_s if t.wall_s > 0 else 0.0,
        "cycle_s_median": float(np.median(cycles)) if cycles else 0.0,
        "cycle_s": [round(float(c), 4) for c in cycles],  # each cycle, for `binpick bench report`
        "motion_s_median": float(np.median(t.motion_s)) if t.motion_s else 0.0,
        "n_bins": float(n_bins),
        "n_attempts": float(t.attempts),
        "n_good": float(t.good),
        "parts_settled": float(t.settled),
        "parts_lost": float(t.lost),
    }


def bench_cell(
    settings: Params,
    names: list[str] | None,
    n_bins: int,
    parts_per_bin: tuple[int, int],
    checkpoints: dict[str, Path],
    seed: int = 0,
    density_kg_m3: float | None = None,
    record_prefix: Path | None = None,
    part_settings: dict[str, Params] | None = None,
) -> dict[str, object]:
    """settings: the project's params (cell.arm, cell.speed_scaling, pick.gripper); checkpoints:
    part -> trained FPCC checkpoint (parts without one are registered over the whole scene);
    record_prefix: the first bin of each part (with the arm's check) recorded to
    <record_prefix>-<part>.rrd; part_settings: the params resolved for a part the project lists
    (its entry's overrides, e.g. a larger suction cup for a heavy part), used for that part."""
    from flows.bench.parts import bench_parts

    if settings.cell.arm is None:
        raise ValueError("cell.arm is null: the cell benchmark needs an arm")
    parts = bench_parts(names, n_points=settings.ingest.n_surface_points)
    per_part: dict[str, dict[str, object]] = {}
    out: dict[str, object] = {
        "machine": machine(),
        "arm": settings.cell.arm,
        "gripper": settings.pick.gripper,
        "speed_scaling": settings.cell.speed_scaling,
        "parts_per_bin": list(parts_per_bin),
        "parts": per_part,
    }
    for part in parts:
        p = picking_settings((part_settings or {}).get(part.name, settings), part)
        layout = cell_layout(p)
        p = p.model_copy(
            update={
                "cell": layout.cell,
                "pick": p.pick.model_copy(update={"T_base_from_cam": layout.T_base_from_cam.tolist()}),
            }
        )
        models = bench_models(part, p, checkpoints.get(part.name))
        density = density_kg_m3 or part_density(p, part.name)
        arm_models = dataclasses.replace(models, cell_params=layout.cell, density_kg_m3=density)
        bare = layout.cell.model_copy(update={"joint_limit_margin_deg": 0.0, "min_singularity": 0.0})
        baseline = ArmPlanner(
            load_arm(layout.cell.arm or "ur5e"),
            bare,
            layout.T_base_from_cam,
            DepthView.empty(),
            np.zeros((0, 4)),
            p.pick.pregrasp_distance_m,
            p.pick.retreat_distance_m,
            check_path=False,
        )
        runs: dict[str, tuple[Tally, list[float]]] = {}
        for name, run_models, planner in (("arm", arm_models, None), ("baseline", models, baseline)):
            total, cycles = Tally(), list[float]()
            with tempfile.TemporaryDirectory(prefix="binpick-cell-") as tmp:
                for b in range(n_bins):
                    bin_seed = derive_seed(seed, "bench-cell", part.name, b)
                    n = int(np.random.default_rng(bin_seed).integers(parts_per_bin[0], parts_per_bin[1] + 1))
                    record = (
                        record_prefix.with_name(f"{record_prefix.name}-{part.name}.rrd")
                        if record_prefix is not None and b == 0 and planner is None
                        else None
                    )
                    one = _clear_bin(
                        part, run_models, p, layout, planner, n, bin_seed, Path(tmp), cycles, density, record
                    )
                    log.info(
                        "%s bin %d (%s): %d of %d removed, %d good of %d executed (%d attempts); failures: %s",
                        part.name,
                        b,
                        name,
                        one.removed,
                        one.settled,
                        one.good,
                        one.executed,
                        one.attempts,
                        dict(one.failures) or "none",
                    )
                    total.add(one)
            runs[name] = (total, cycles)
        arm_tally, arm_cycles = runs["arm"]
        base_tally, base_cycles = runs["baseline"]
        per_part[part.name] = {
            **_keys(arm_tally, arm_cycles, n_bins),
            "failures": dict(arm_tally.failures),
            **{f"baseline_{k}": v for k, v in _keys(base_tally, base_cycles, n_bins).items()},
            "baseline_failures": dict(base_tally.failures),
            "mass_kg": part_mass_kg(part, density),
            "holding_force_n": holding_force_n(p.pick, p.pick.gripper),
            "bin_inner_m": [p.generate.bin.inner_x_m, p.generate.bin.inner_y_m],
            "base_to_bin_centre_m": float(np.linalg.norm(layout.T_bin_from_base[:2, 3])),
        }
    return out
