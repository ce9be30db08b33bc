"""`binpick cell run`: the cell's loop, capture -> picks -> move -> grasp -> place, until the bin is
empty, a stop is asked for (Ctrl-C, SIGTERM, or the file data/cell/STOP), the arm stops itself, or
--max-failures attempts in a row fail (3). The robot is cell.robot.driver's: the physics cell
(a bin of the part settled in it, seen by the rendered camera) or a Universal Robots arm through
ur_rtde (the camera then is the Zivid of zivid_camera).

Every cycle is kept for review like a service request, in data/cell/runs/<run>/<cycle>/: the
capture (capture.zdf), picks.json, and cycle.json: its state (placed, no part found, no pick found,
no grip, grasp lost, arm stopped, bin empty, the capture was refused: why), the pick taken, the
joint path, the timings.
"""

from __future__ import annotations

import json
import logging
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Protocol

import numpy as np

from binpick.cell.retries import FailedGrips
from binpick.cell.robot import (
    ARM_STOPPED,
    GRASP_LOST,
    MAX_FAILURES_IN_A_ROW,
    NO_GRIP,
    PICKS_PER_CAPTURE,
    Robot,
    URRobot,
    execute_pick,
)
from binpick.cell.simulation import SimulatedCell
from binpick.errors import BinpickError, NothingAboveTheFloor
from binpick.io.atomic import write_text
from binpick.io.capture import Capture
from binpick.io.part_model import PartModel
from binpick.io.picks import picks_document, write_picks_document
from binpick.io.zdf import save_zdf_v1
from binpick.layout import Layout
from binpick.params import Params
from binpick.part.model import density_kg_m3
from binpick.robot.arm import load_arm
from binpick.robot.trajectory import JointLimits
from binpick.scene.process import PartModels, SceneResult, process
from binpick.seeding import SceneSeeds, capture_digest

log = logging.getLogger("binpick.cell")

# States of a cycle besides execute_pick's.
# A bin is empty when cleaning leaves nothing above its floor inside its walls.
NO_PART, NO_PICK, BIN_EMPTY = "no part found", "no pick found", "bin empty"


class Camera(Protocol):
    def grab(self) -> Capture: ...


@dataclass
class RunSummary:
    """The run: its folder, cycles, parts placed, and why it ended."""

    folder: Path
    cycles: int
    placed: int
    ended: str


class SimulatedCamera:
    """The camera of the physics cell: the bin and its parts rendered as they lie now (sensor noise
    from generate.noise), straight above the bin floor at camera.distance_m."""

    def __init__(self, sim: SimulatedCell, part: PartModel, params: Params, seed: int) -> None:
        from binpick.view import ViewParams

        self.sim, self.part, self.params = sim, part, params
        self.view = ViewParams.of_import(params.import_capture)
        self.rng = np.random.default_rng(seed)

    def grab(self) -> Capture:
        from binpick.generation.bin import T_bin_from_cam
        from binpick.generation.scene import render_scene

        inside = self.sim.in_bin()
        poses, index = self.sim.part_poses()
        keep = [k for k, i in enumerate(index) if inside[i]]
        p = self.params
        scene = render_scene(
            self.part, poses[keep], p.generate, p.camera, self.view, self.rng, T_bin_from_cam(p.camera.distance_m)
        )
        H, W = scene.labels.shape
        return Capture(xyz_m=scene.xyz_m.reshape(-1, 3).astype(np.float32), rgb=None, shape=(H, W))


class ZividCamera:
    """The cell's Zivid camera (zivid_camera settings)."""

    def __init__(self, params: Params) -> None:
        from binpick.cell.zivid_camera import import_zivid

        self.zivid, self.settings = import_zivid(), params.zivid_camera

    def grab(self) -> Capture:
        from binpick.cell.zivid_camera import grab_frame

        data = grab_frame(self.zivid, self.settings)
        return Capture(xyz_m=data.xyz / 1000.0, rgb=data.rgb, shape=data.shape)


def simulated_cell(params: Params, part: PartModel, n_parts: int, seed: int) -> tuple[SimulatedCell, Camera]:
    """A physics cell of n_parts of the part settled in the project's bin (params resolved for it),
    the arm where pick.T_base_from_cam puts it with the camera straight above the bin floor at
    camera.distance_m; and that camera."""
    from binpick.cell.simulation import SimulatedCell
    from binpick.generation.bin import T_bin_from_cam, bin_meshes
    from binpick.generation.camera import camera_of
    from binpick.generation.placement import place_objects
    from binpick.generation.scene import settle_in_bin
    from binpick.geometry.camera import in_view_of
    from binpick.geometry.transforms import invert_T

    if params.pick.T_base_from_cam is None:
        raise BinpickError("the simulated cell needs pick.T_base_from_cam (where the arm stands beside the bin)")
    if params.cell.arm is None:
        raise BinpickError("the cell needs an arm: cell.arm is null")
    g = params.generate
    rng = np.random.default_rng(seed)
    placed = place_objects(part.points_m, n_parts, g.bin, g.placement, rng)
    T_bin = settle_in_bin(part, placed.T_bin_from_model, g, rng)
    T_bin_from_camera = T_bin_from_cam(params.camera.distance_m)
    T_bin_from_base = T_bin_from_camera @ invert_T(np.asarray(params.pick.T_base_from_cam, dtype=float))
    sim = SimulatedCell(
        load_arm(params.cell.arm),
        params.cell,
        params.pick,
        params.pick.gripper,
        part,
        density_kg_m3(params, part.name),
        [(m.bounds[0], m.bounds[1]) for m in bin_meshes(g.bin)],
        (g.bin.inner_x_m / 2.0, g.bin.inner_y_m / 2.0),
        T_bin_from_base,
        T_bin,
        in_view_of(camera_of(params.camera), invert_T(T_bin_from_camera)),
    )
    return sim, SimulatedCamera(sim, part, params, seed)


def run_cell(
    root: Path,
    params: Params,
    part: str,
    robot: Robot,
    camera: Camera,
    models: PartModels,
    max_cycles: int | None = None,
    stop: threading.Event | None = None,
    max_failures: int = MAX_FAILURES_IN_A_ROW,
) -> RunSummary:
    """The loop; every cycle kept under data/cell/runs/<run>/."""
    layout = Layout(root)
    folder = layout.cell_runs / datetime.now(UTC).strftime("%Y-%m-%dT%H-%M-%S")
    folder.mkdir(parents=True, exist_ok=True)
    stop = stop or threading.Event()
    failures, placed, cycle = 0, 0, 0
    failed_grips = FailedGrips()  # parts left alone until nothing else is left (binpick/cell/retries.py)
    ended = "stopped"
    while True:
        if stop.is_set() or layout.cell_stop.exists():
            ended = "stop requested"
            break
        if max_cycles is not None and cycle >= max_cycles:
            ended = f"{max_cycles} cycles done"
            break
        if failures >= max_failures:
            ended = f"{failures} attempts in a row failed"
            break
        t0 = time.perf_counter()
        capture = camera.grab()
        t_capture = time.perf_counter() - t0
        q = robot.joints()
        digest = capture_digest(capture.xyz_m, capture.rgb)
        try:
            result: SceneResult | None = process(
                capture.xyz_m,
                capture.rgb,
                capture.shape,
                models,
                SceneSeeds.of_capture_digest(params.seed, digest),
                q,
                PICKS_PER_CAPTURE,
                failed_grips,
            )
            refused = None
        except NothingAboveTheFloor as exc:
            result, refused = None, f"{BIN_EMPTY}: {exc}"
        except BinpickError as exc:
            result, refused = None, f"the capture was refused: {exc}"
        t_plan = time.perf_counter() - t0 - t_capture
        here = folder / f"{cycle:04d}"
        here.mkdir()
        if capture.shape is not None:
            save_zdf_v1(here / "capture.zdf", capture.xyz_m.reshape(*capture.shape, 3) * 1000.0)
        plan = result.picks if result is not None else None
        record: dict[str, object] = {
            "cycle": cycle,
            "part": part,
            "capture_s": round(t_capture, 4),
            "plan_s": round(t_plan, 4),
        }
        if plan is not None:
            T_base = np.asarray(params.pick.T_base_from_cam) if params.pick.T_base_from_cam is not None else None
            write_picks_document(
                here / "picks.json",
                picks_document(
                    f"{folder.name}/{here.name}", part, params.pick.gripper, plan, T_base, params.pick.pose_format
                ),
            )
        cycle += 1
        if refused is not None:
            state = refused
        elif result is None or not result.registration.poses:
            state = NO_PART
        elif plan is None or not plan.picks or plan.picks[0].arm is None:
            state = NO_PICK
        else:
            first = plan.picks[0]
            assert first.arm is not None
            record.update(
                pose_index=first.pose_index,
                grasp_id=first.grasp_id,
                path=list(first.arm.path),
                joints_rad={n: [round(float(x), 6) for x in first.arm.q[n]] for n in first.arm.path},
            )
            t1 = time.perf_counter()
            state = execute_pick(robot, first.arm, first.width_m)
            record["move_s"] = round(time.perf_counter() - t1, 4)
            if state in (NO_GRIP, GRASP_LOST):
                failed_grips.failed(
                    result.registration.poses[first.pose_index].T_cam_from_model,
                    models.part.centre_m,
                    first.T_cam_from_grasp,
                    held=state == GRASP_LOST,
                )
        record["state"] = state
        write_text(here / "cycle.json", json.dumps(record, indent=1) + "\n")
        log.info("cycle %d: %s", cycle - 1, state)
        if state == "placed":
            placed += 1
            failures = 0
        elif state.startswith(BIN_EMPTY):
            ended = BIN_EMPTY
            break
        elif state == ARM_STOPPED:
            ended = "arm stopped: look at the arm before running again"
            break
        elif state == NO_PICK and failed_grips.retry():
            log.info("no other pick: the parts the gripper failed to hold are tried again")
        else:
            failures += 1
    summary = RunSummary(folder, cycle, placed, ended)
    write_text(folder / "run.json", json.dumps({"cycles": cycle, "placed": placed, "ended": ended}, indent=1) + "\n")
    return summary


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """Ctrl-C and SIGTERM ask the loop to stop after the cycle it is in (the arm is not left
    holding a part mid-air)."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in previous:
        signal.signal(s, lambda *_: stop.set())
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def real_robot(params: Params) -> URRobot:
    arm = load_arm(params.cell.arm or "ur5e")
    r = params.cell.robot
    limits = JointLimits(arm.max_velocity_rad_s, arm.max_acceleration_rad_s2).scaled(params.cell.speed_scaling)
    return URRobot(r.host, limits, r.vacuum_out, r.vacuum_in, r.grip_s, r.release_s)
