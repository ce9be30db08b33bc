"""The running cell: the loop against the simulated robot, the real robot's driver against a fake
of ur_rtde's Python API, and the physics of a hold; each recovers a known answer."""

from __future__ import annotations

import dataclasses
import json
import threading

import numpy as np
import pytest
from conftest import ROOT

from binpick.cell.robot import ARM_STOPPED, GRASP_LOST, NO_GRIP, RobotStopped, URRobot, execute_pick
from binpick.cell.simulation import SCALE
from binpick.errors import BinpickError
from binpick.layout import Layout
from binpick.params import load_params
from binpick.picking.arm import ArmMotion
from binpick.picking.plan import GRIP_FAILED
from binpick.robot.trajectory import JointLimits

PARAMS = load_params(ROOT / "params.yaml", "t_joint")
PATH = ("pregrasp", "grasp", "lift", "place_above", "place")


@pytest.fixture(scope="module")
def models(t_joint):
    # Registration over the whole scene (no network), grasps generated, the arm checked.
    import dataclasses

    from flows.bench.picking import bench_models

    return dataclasses.replace(bench_models(t_joint, PARAMS, None), cell_params=PARAMS.cell)


def test_the_cell_empties_a_simulated_bin_and_keeps_every_cycle(tmp_path, t_joint, models):
    from flows.cell_run import run_cell, simulated_cell

    sim, camera = simulated_cell(PARAMS, t_joint, 3, seed=4)
    start = len(sim.part_poses()[1])
    summary = run_cell(tmp_path, PARAMS, "t_joint", sim, camera, models, max_cycles=6)
    left = int(sim.in_bin().sum())
    sim.close()
    cycles = sorted(p for p in summary.folder.iterdir() if p.is_dir())
    states = [json.loads((c / "cycle.json").read_text())["state"] for c in cycles]
    assert len(cycles) == summary.cycles and states.count("placed") == summary.placed
    # Every part placed left the bin, and only those.
    assert start == 3 and left == start - summary.placed and summary.placed >= 2
    for c, state in zip(cycles, states, strict=True):
        assert (c / "capture.zdf").is_file()
        if state == "placed":
            record = json.loads((c / "cycle.json").read_text())
            pick = json.loads((c / "picks.json").read_text())["picks"][0]
            assert record["path"] == pick["arm"]["path"] and record["joints_rad"]["grasp"] == pytest.approx(
                pick["arm"]["joints_rad"]["grasp"], abs=1e-6
            )
    assert summary.ended in ("bin empty", "6 cycles done", "3 attempts in a row failed")


def test_a_stop_request_ends_the_run_before_the_next_cycle(tmp_path, models):
    from flows.cell_run import run_cell

    class Untouched:
        def grab(self):
            raise AssertionError("no capture after a stop")

    Layout(tmp_path).cell_stop.parent.mkdir(parents=True)
    Layout(tmp_path).cell_stop.touch()
    summary = run_cell(tmp_path, PARAMS, "t_joint", None, Untouched(), models)  # type: ignore[arg-type]
    assert summary.cycles == 0 and summary.ended == "stop requested"
    stop = threading.Event()
    stop.set()
    Layout(tmp_path).cell_stop.unlink()
    assert run_cell(tmp_path, PARAMS, "t_joint", None, Untouched(), models, stop=stop).ended == "stop requested"  # type: ignore[arg-type]


@pytest.mark.parametrize("failure", [NO_GRIP, GRASP_LOST])
def test_a_part_the_gripper_failed_to_hold_is_left_alone_in_the_next_cycle(tmp_path, t_joint, models, failure):
    """The first grip fails, at the grasp (no vacuum) or on the way up (the part torn off where
    it lay): the next cycle leaves that part alone and picks another."""
    from flows.cell_run import run_cell, simulated_cell

    sim, camera = simulated_cell(PARAMS, t_joint, 3, seed=4)

    class FailsOnce:
        """The simulated robot, its first grip failing (the part is not moved)."""

        def __init__(self):
            self.failed = False

        def grip(self, width_m):
            if not self.failed:
                self.failed = True
                # NO_GRIP: the vacuum sensor says nothing is held; GRASP_LOST: it says the part is
                # held at the grasp and then nothing is (torn off as the lift starts, where it lay).
                return failure == GRASP_LOST
            return sim.grip(width_m)

        def __getattr__(self, name):
            return getattr(sim, name)

    summary = run_cell(tmp_path, PARAMS, "t_joint", FailsOnce(), camera, models, max_cycles=2)  # type: ignore[arg-type]
    sim.close()
    first, second = sorted(p for p in summary.folder.iterdir() if p.is_dir())
    assert json.loads((first / "cycle.json").read_text())["state"] == failure
    assert json.loads((second / "cycle.json").read_text())["state"] == "placed"
    tried, then = (json.loads((c / "picks.json").read_text()) for c in (first, second))
    assert [u["reason"] for u in then["unpicked"]].count(GRIP_FAILED) == 1
    # The second pick went to another part: its grasp lies a part's width away from the first.
    grasp = [np.asarray(d["picks"][0]["camera"]["grasp"])[:3, 3] for d in (tried, then)]
    assert np.linalg.norm(grasp[0] - grasp[1]) > 0.02


class FakeRTDE:
    """ur_rtde's three interfaces, recording what they are sent."""

    def __init__(self, vacuum: list[bool], move_ok: bool = True, protective: bool = False) -> None:
        self.moves: list[list[list[float]]] = []
        self.outputs: list[tuple[int, bool]] = []
        fake = self

        class Control:
            def __init__(self, host):
                fake.host = host

            def moveJ(self, path, asynchronous=False):
                fake.moves.append(path)
                return move_ok

            def moveL_FK(self, q, speed, acceleration, asynchronous=False):
                fake.moves.append([[*q, speed, acceleration, "line"]])
                return move_ok

            def stopScript(self):
                pass

            def disconnect(self):
                fake.disconnected = True

        class Receive:
            def __init__(self, host):
                pass

            def getActualQ(self):
                return [0.1] * 6

            def getDigitalInState(self, pin):
                return vacuum.pop(0)

            def isEmergencyStopped(self):
                return False

            def isProtectiveStopped(self):
                return protective

        class IO:
            def __init__(self, host):
                pass

            def setStandardDigitalOut(self, pin, value):
                fake.outputs.append((pin, value))

        self.modules = tuple(
            type("m", (), {name: cls})
            for name, cls in (
                ("RTDEControlInterface", Control),
                ("RTDEReceiveInterface", Receive),
                ("RTDEIOInterface", IO),
            )
        )


def _motion() -> ArmMotion:
    q = {name: np.full(6, 0.1 * (k + 1)) for k, name in enumerate(PATH)}
    return ArmMotion(q, 0.0, np.eye(4), 3.0, PATH)


def _robot(fake: FakeRTDE, vacuum_in: int | None = 3) -> URRobot:
    limits = JointLimits(np.array([3.1, 3.1, 3.1, 6.2, 6.2, 6.2]), np.full(6, 2.5)).scaled(0.5)
    return URRobot("10.0.0.5", limits, 1, vacuum_in, 0.0, 0.0, fake.modules)


def test_the_real_arm_is_sent_the_plan_and_its_vacuum_is_read():
    fake = FakeRTDE(vacuum=[True, True])
    robot = _robot(fake)
    assert execute_pick(robot, _motion()) == "placed"
    # To the grasp, then out and over to the place: each configuration at rest (blend 0), at the
    # slowest joint's speed and acceleration times the scaling.
    assert [[m[:6] for m in move] for move in fake.moves] == [
        [[0.1] * 6, [0.2] * 6],
        [[pytest.approx(0.3)] * 6, [0.4] * 6, [0.5] * 6],
    ]
    assert all(m[6:] == [pytest.approx(1.55), pytest.approx(0.625), 0.0] for move in fake.moves for m in move)
    assert fake.outputs == [(1, True), (1, False)] and fake.host == "10.0.0.5"
    assert robot.joints() == pytest.approx([0.1] * 6)
    # A part carried at half the speed (the gripper's hold): the moves after the grasp at half the
    # speed and a quarter of the acceleration, the way down at the full.
    slow = FakeRTDE(vacuum=[True, True])
    assert execute_pick(_robot(slow), dataclasses.replace(_motion(), carry_share=0.5)) == "placed"
    assert all(m[6:] == [pytest.approx(1.55), pytest.approx(0.625), 0.0] for m in slow.moves[0])
    assert all(m[6:] == [pytest.approx(0.775), pytest.approx(0.15625), 0.0] for m in slow.moves[1])


def test_the_lift_is_sent_as_the_controllers_straight_line():
    # A chain of configurations to the lift (the plan's straight line up): the real arm gets one
    # moveL_FK to its end, between the joint moves, at the carry's share of the line speed.
    chain = np.linspace(np.full(6, 0.2), np.full(6, 0.3), 5)
    motion = dataclasses.replace(_motion(), lines={"lift": chain}, carry_share=0.5)
    fake = FakeRTDE(vacuum=[True, True])
    assert execute_pick(_robot(fake), motion) == "placed"
    assert [[m[:6] for m in move] for move in fake.moves] == [
        [[0.1] * 6, [0.2] * 6],
        [[pytest.approx(0.3)] * 6],
        [[0.4] * 6, [0.5] * 6],
    ]
    assert fake.moves[1][0][6:] == [pytest.approx(0.125), pytest.approx(0.3), "line"]


def test_no_vacuum_at_the_grasp_and_a_lost_part_and_a_stop_are_named():
    fake = FakeRTDE(vacuum=[False])
    assert execute_pick(_robot(fake), _motion()) == NO_GRIP
    # The vacuum is switched off again and the arm backs out along the approach.
    assert fake.outputs == [(1, True), (1, False)] and [m[:6] for m in fake.moves[-1]] == [[0.1] * 6]
    assert execute_pick(_robot(FakeRTDE(vacuum=[True, False])), _motion()) == GRASP_LOST
    stopped = FakeRTDE(vacuum=[True], move_ok=False, protective=True)
    assert execute_pick(_robot(stopped), _motion()) == ARM_STOPPED
    with pytest.raises(RobotStopped, match="protective stop"):
        _robot(stopped).move([np.zeros(6)])


def test_without_ur_rtde_the_real_driver_says_what_to_install(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "rtde_control", None)
    limits = JointLimits(np.full(6, 3.1), np.full(6, 2.5))
    with pytest.raises(BinpickError, match=r"pip install -e \.\[robot\]"):
        URRobot("10.0.0.5", limits, 0, None, 0.0, 0.0)


def test_the_cup_lifts_a_part_within_its_holding_force_and_loses_a_heavier_one(t_joint, models):
    from flows.cell_run import simulated_cell

    outcomes = {}
    for density in (2700.0, 2700.0 * 40):  # 0.05 kg, and 1.9 kg: 18 N on a 4.5 N cup
        p = PARAMS.model_copy(
            update={"parts": {"t_joint": PARAMS.parts["t_joint"].model_copy(update={"density_kg_m3": density})}}
        )
        sim, camera = simulated_cell(p, t_joint, 1, seed=2)
        capture = camera.grab()
        from binpick.scene.process import process
        from binpick.seeding import SceneSeeds

        plan = process(capture.xyz_m, None, capture.shape, models, SceneSeeds.of(0, "hold"), sim.joints()).picks
        assert plan is not None and plan.picks and plan.picks[0].arm is not None
        outcomes[density] = sim.execute(plan.picks[0].arm, sim.joints()).outcome
        sim.close()
    assert outcomes == {2700.0: "placed", 2700.0 * 40: "dropped"}


def test_backing_out_of_a_grip_that_did_not_seal_is_not_a_touch(t_joint, models):
    """The vacuum fails at the grasp: the cup leaves the part it stood on, back to the pre-grasp.
    The judge names the pick "no seal" and nothing touched (it had counted the part the cup left)."""
    from binpick.scene.process import process
    from binpick.seeding import SceneSeeds
    from flows.cell_run import simulated_cell

    sim, camera = simulated_cell(PARAMS, t_joint, 1, seed=2)
    capture = camera.grab()
    plan = process(capture.xyz_m, None, capture.shape, models, SceneSeeds.of(0, "hold"), sim.joints()).picks
    assert plan is not None and plan.picks and plan.picks[0].arm is not None
    sim.grip = lambda width_m: False  # type: ignore[method-assign]
    done = sim.execute(plan.picks[0].arm, sim.joints())
    left = int(sim.in_bin().sum())
    sim.close()
    assert done.outcome == "no seal" and done.touched == set()
    assert left == 1


def test_a_part_on_the_heap_above_the_rim_is_in_the_bin_and_one_beside_it_is_not(t_joint):
    """A full bin's heap rises above the walls: a part resting there is still in the bin (it is
    rendered, and not counted as come out with a pick); a part beside the walls is not."""
    from flows.cell_run import simulated_cell

    sim, _ = simulated_cell(PARAMS, t_joint, 1, seed=2)
    body, b = sim.parts[0], PARAMS.generate.bin

    def in_bin_at(xyz_m):
        _, q = sim.pb.getBasePositionAndOrientation(body, physicsClientId=sim.client)
        sim.pb.resetBasePositionAndOrientation(body, list(np.asarray(xyz_m) * SCALE), q, physicsClientId=sim.client)
        return bool(sim.in_bin()[0])

    above_the_rim = in_bin_at([0.0, 0.0, b.wall_height_m + 0.05])
    beside = in_bin_at([b.inner_x_m / 2 + 0.05, 0.0, 0.02])
    sim.close()
    assert above_the_rim and not beside


def test_the_jaws_close_across_a_lone_part_and_carry_it_to_the_place_touching_nothing_else(t_joint):
    """The jaw gripper with pads at the fingers' tips (whole-finger pads put the fingertips into
    the floor under a lying pipe: no grasp) on a lone T-joint: the jaws come down around the
    part, close on it by friction and carry it to the place, touching nothing on the way."""
    from binpick.params import Params
    from binpick.scene.process import process
    from binpick.seeding import SceneSeeds
    from flows.bench.picking import bench_models
    from flows.cell_run import simulated_cell

    raw = PARAMS.model_dump(by_alias=True)
    raw["pick"].update(gripper="jaw", jaw={**raw["pick"]["jaw"], "pad_length_m": 0.01})
    raw["cell"]["T_flange_from_tcp"] = None  # mounted as modelled
    p = Params.model_validate(raw)
    # The jaw tool on the flange: 0.12 + palm 0.02 + the 0.03 finger less half its 0.01 pad.
    assert np.asarray(p.cell.T_flange_from_tcp)[2, 3] == pytest.approx(0.165)
    jaw_models = dataclasses.replace(bench_models(t_joint, p, None), cell_params=p.cell)
    sim, camera = simulated_cell(p, t_joint, 1, seed=2)
    capture = camera.grab()
    plan = process(capture.xyz_m, None, capture.shape, jaw_models, SceneSeeds.of(0, "jaw"), sim.joints()).picks
    assert plan is not None and plan.picks and plan.picks[0].arm is not None
    done = sim.execute(plan.picks[0].arm, sim.joints(), plan.picks[0].width_m)
    sim.close()
    assert (done.outcome, done.touched) == ("placed", set())


def test_the_bin_is_at_rest_in_the_cells_world_before_the_first_capture(t_joint):
    """A part handed over 20 mm above where it rests (a pose from another world's physics) has
    come down to rest before the cell's first capture: the camera shows what the arm will meet."""
    from binpick.cell.simulation import SimulatedCell
    from binpick.generation.bin import bin_meshes
    from binpick.part.model import density_kg_m3
    from binpick.robot.arm import load_arm
    from flows.cell_run import simulated_cell

    sim, _ = simulated_cell(PARAMS, t_joint, 1, seed=2)
    (rest,), _ = sim.part_poses()
    T_bin_from_base, in_view = sim.T_bin_from_base, sim.in_view
    sim.close()
    raised = rest.copy()
    raised[2, 3] += 0.02
    b = PARAMS.generate.bin
    sim = SimulatedCell(
        load_arm(PARAMS.cell.arm or "ur5e"), PARAMS.cell, PARAMS.pick, PARAMS.pick.gripper, t_joint,
        density_kg_m3(PARAMS, t_joint.name), [(m.bounds[0], m.bounds[1]) for m in bin_meshes(b)],
        (b.inner_x_m / 2.0, b.inner_y_m / 2.0), T_bin_from_base, raised[None], in_view,
    )  # fmt: skip
    (first,), _ = sim.part_poses()
    sim.close()
    assert abs(first[2, 3] - rest[2, 3]) < 0.002
    assert np.allclose(first[:3, :3], rest[:3, :3], atol=0.02)
