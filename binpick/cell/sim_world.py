"""Building the simulated cell's world in pybullet (binpick/cell/simulation.py): the table and the
bin as static boxes, a part as a rigid body of its convex pieces, the arm from its URDF and the
tool as one body of the gripper's primitives. Lengths at the interface in metres, bin frame; the
simulator's world is scaled by generation.physics.SCALE."""

from __future__ import annotations

import numpy as np

from binpick.generation.physics import SCALE, quaternion_xyzw
from binpick.geometry.transforms import make_T
from binpick.native import stdout_silenced
from binpick.params import PickParams
from binpick.picking.gripper import Box, Cylinder, gripper_primitives, surface_points
from binpick.robot.arm import ArmModel

FRICTION = 0.6


def add_boxes(pb, client: int, boxes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list[int], dict[int, str]]:
    """Static boxes (lo, hi corners, bin frame, metres) under a table reaching 3 m around: the
    bodies and what each is ("table" for the lowest, "bin" for the rest)."""
    ground_top = min(float(hi[2]) for _, hi in boxes) if boxes else 0.0
    table = (np.array([-3.0, -3.0, ground_top - 0.05]), np.array([3.0, 3.0, ground_top]))
    bodies, names = [], {}
    for lo, hi in [table, *boxes]:
        half = (np.asarray(hi) - np.asarray(lo)) / 2.0 * SCALE
        middle = (np.asarray(hi) + np.asarray(lo)) / 2.0 * SCALE
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client)
        body = pb.createMultiBody(0.0, shape, basePosition=middle.tolist(), physicsClientId=client)
        pb.changeDynamics(body, -1, lateralFriction=FRICTION, physicsClientId=client)
        bodies.append(body)
        names[body] = "table" if float(hi[2]) <= ground_top else "bin"
    return bodies, names


def add_part(pb, client: int, shape: int, mass_kg: float, T_bin_from_body: np.ndarray) -> int:
    """A part's rigid body at a pose (4, 4), bin frame, metres."""
    T = np.asarray(T_bin_from_body, dtype=float)
    body = pb.createMultiBody(
        mass_kg,
        shape,
        basePosition=(T[:3, 3] * SCALE).tolist(),
        baseOrientation=quaternion_xyzw(T[:3, :3]).tolist(),
        physicsClientId=client,
    )
    pb.changeDynamics(
        body,
        -1,
        lateralFriction=FRICTION,
        restitution=0.0,
        linearDamping=0.1,
        angularDamping=0.1,
        physicsClientId=client,
    )
    return int(body)


def add_arm(pb, client: int, arm: ArmModel, T_bin_from_base: np.ndarray) -> tuple[int, list[int], dict[int, int]]:
    """The arm from its URDF with its controller base at T_bin_from_base: the body, the
    simulator's joint of each of the arm's joints, and the simulator's link of each moving link
    of the arm model (arm model link index -> simulator link)."""
    # pybullet's root is the URDF's base_link, the controller's base turned half a turn about z.
    T = np.asarray(T_bin_from_base, dtype=float) @ make_T(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))
    # pybullet notes every URDF link without inertia on stdout.
    with stdout_silenced():
        body = pb.loadURDF(
            str(arm.urdf_path),
            basePosition=(T[:3, 3] * SCALE).tolist(),
            baseOrientation=quaternion_xyzw(T[:3, :3]).tolist(),
            useFixedBase=True,
            globalScaling=SCALE,
            physicsClientId=client,
        )
    info = [
        pb.getJointInfo(body, j, physicsClientId=client) for j in range(pb.getNumJoints(body, physicsClientId=client))
    ]
    names = {joint[1].decode(): j for j, joint in enumerate(info)}
    # The links that move (the base and its cable connector stand beside the bin).
    child = {joint[12].decode(): j for j, joint in enumerate(info)}
    links = {k: child[name] for k, name in enumerate(arm.link_names) if k > 0 and name in child}
    return int(body), [names[name] for name in arm.joint_names], links


def add_tool(pb, client: int, pick: PickParams, kind: str) -> tuple[int, np.ndarray]:
    """The gripper's primitives (picking/gripper.py) as one body in the tool frame, and points on
    its surface (n, 3), tool frame, metres."""
    primitives = gripper_primitives(pick, kind, pick.jaw.opening_max_m)
    shapes, positions = [], []
    for prim in primitives:
        if isinstance(prim, Cylinder):
            length = prim.z1 - prim.z0
            shapes.append(
                pb.createCollisionShape(
                    pb.GEOM_CYLINDER, radius=prim.radius * SCALE, height=length * SCALE, physicsClientId=client
                )
            )
            positions.append([0.0, 0.0, (prim.z0 + prim.z1) / 2.0 * SCALE])
        elif isinstance(prim, Box):
            half = (prim.hi - prim.lo) / 2.0 * SCALE
            shapes.append(pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client))
            positions.append(((prim.hi + prim.lo) / 2.0 * SCALE).tolist())
    n = len(shapes)
    body = pb.createMultiBody(
        0.0,
        -1,
        linkMasses=[0.0] * n,
        linkCollisionShapeIndices=shapes,
        linkVisualShapeIndices=[-1] * n,
        linkPositions=positions,
        linkOrientations=[[0, 0, 0, 1]] * n,
        linkInertialFramePositions=[[0, 0, 0]] * n,
        linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
        linkParentIndices=[0] * n,
        linkJointTypes=[pb.JOINT_FIXED] * n,
        linkJointAxis=[[0, 0, 1]] * n,
        physicsClientId=client,
    )
    return int(body), surface_points(primitives, 0.01)
