"""Physically settled piles: objects dropped into the bin and left to settle under gravity in a
rigid-body simulation (pybullet), for piles that look like a real bin (objects leaning on each
other, sliding under overhangs, lying in stable poses).

The part collides through a convex decomposition of its mesh (V-HACD), computed once per mesh
and kept in the system's temporary folder for every process and run. The simulation runs with
lengths scaled up (SCALE), because Bullet's contact
margins and tolerances are tuned for objects of about a metre; parts of a few centimetres would
otherwise float millimetres apart or sink into each other.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from binpick.geometry.transforms import invert_T, make_T
from binpick.native import stdout_silenced

log = logging.getLogger(__name__)

SCALE = 10.0  # simulation length unit = 1/SCALE metre (decimetres)
TIME_STEP_S = 1.0 / 240.0
REST_SPEED_M_S = 0.002  # settled when every object moves slower than this
VHACD_VERSION = 1  # in the cached decomposition's file name: bump when its settings change


@dataclass(frozen=True)
class SettleSettings:
    max_time_s: float = 2.0
    friction: float = 0.6
    drop_gap_m: float = 0.005  # objects start this far above their drop-placement pose, per object


def convex_parts_obj(vertices_m: np.ndarray, faces: np.ndarray) -> str:
    """Path of an OBJ holding the V-HACD convex decomposition of the mesh (scaled by SCALE)."""
    import pybullet as pb

    key = hashlib.sha1(
        np.ascontiguousarray(vertices_m, np.float64).tobytes() + np.ascontiguousarray(faces, np.int64).tobytes()
    ).hexdigest()
    # One file per mesh in the system's temporary folder, shared by worker processes and runs.
    out = Path(tempfile.gettempdir()) / f"binpick-vhacd-{VHACD_VERSION}-{key[:16]}.obj"
    if out.is_file() and out.stat().st_size > 0:
        return str(out)
    with tempfile.TemporaryDirectory(prefix="binpick-vhacd-", dir=out.parent) as folder:
        src, parts = Path(folder) / "part.obj", Path(folder) / "parts.obj"
        v = vertices_m * SCALE
        lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
        src.write_text("\n".join(lines) + "\n")
        client = pb.connect(pb.DIRECT)
        try:
            with stdout_silenced():  # V-HACD prints its progress from C
                pb.vhacd(
                    str(src),
                    str(parts),
                    str(Path(folder) / "vhacd.log"),
                    resolution=200000,
                    maxNumVerticesPerCH=64,
                    physicsClientId=client,
                )
        finally:
            pb.disconnect(client)
        if not parts.is_file() or parts.stat().st_size == 0:
            raise RuntimeError("V-HACD convex decomposition of the part failed")
        os.replace(parts, out)  # atomic: a worker reading it sees the whole file or none
    return str(out)


def settle(
    vertices_m: np.ndarray,
    faces: np.ndarray,
    T_bin_from_model: np.ndarray,
    bin_boxes: list[tuple[np.ndarray, np.ndarray]],
    settings: SettleSettings,
    inner_half_xy_m: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Let objects of one part starting at non-overlapping poses fall and settle in the bin.

    vertices_m, faces : the part's mesh, model frame, metres
    T_bin_from_model  : (k, 4, 4) start poses, bin frame (z up, floor at z = 0), metres
    bin_boxes         : static boxes (lo, hi), each (3,) bin frame, metres: floor and walls
    inner_half_xy_m   : half the bin's inner size in x and y, metres
    Returns the settled poses (k, 4, 4) and a (k,) bool mask of objects whose centre is still
    inside the bin (above the floor, between the walls).
    The simulation is deterministic for the same inputs.
    """
    kinds = np.zeros(len(T_bin_from_model), np.int64)
    return settle_kinds([(vertices_m, faces)], kinds, T_bin_from_model, bin_boxes, settings, inner_half_xy_m)


def settle_kinds(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    kinds: np.ndarray,
    T_bin_from_model: np.ndarray,
    bin_boxes: list[tuple[np.ndarray, np.ndarray]],
    settings: SettleSettings,
    inner_half_xy_m: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """settle for a bin of several kinds of part: meshes (vertices_m, faces) per kind, model
    frame, metres; kinds (k,) int the kind of each object. Returns as settle does."""
    import pybullet as pb

    k = len(T_bin_from_model)
    if k == 0:
        return T_bin_from_model.copy(), np.zeros(0, bool)
    kinds = np.asarray(kinds, dtype=np.int64)
    # Bodies live in a frame at the centre of the part's box: a CAD origin far from the part
    # would otherwise be the centre of mass, and the point tested for being in the bin.
    centres = [(v.min(axis=0) + v.max(axis=0)) / 2.0 for v, _ in meshes]
    T_model_from_body = [make_T(np.eye(3), c) for c in centres]
    shape_files = [convex_parts_obj(v - c, f) for (v, f), c in zip(meshes, centres, strict=True)]
    client = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81 * SCALE, physicsClientId=client)
        pb.setTimeStep(TIME_STEP_S, physicsClientId=client)
        pb.setPhysicsEngineParameter(numSolverIterations=50, deterministicOverlappingPairs=1, physicsClientId=client)
        for lo, hi in bin_boxes:
            half = (np.asarray(hi) - np.asarray(lo)) / 2.0 * SCALE
            middle = (np.asarray(hi) + np.asarray(lo)) / 2.0 * SCALE
            box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client)
            body = pb.createMultiBody(0.0, box, basePosition=middle.tolist(), physicsClientId=client)
            pb.changeDynamics(body, -1, lateralFriction=settings.friction, physicsClientId=client)
        shapes = [pb.createCollisionShape(pb.GEOM_MESH, fileName=f, physicsClientId=client) for f in shape_files]
        bodies = []
        for i, T in enumerate(T_bin_from_model):
            T_body = T @ T_model_from_body[kinds[i]]
            position = (T_body[:3, 3] + np.array([0.0, 0.0, settings.drop_gap_m * (i + 1)])) * SCALE
            body = pb.createMultiBody(
                1.0,
                shapes[kinds[i]],
                basePosition=position.tolist(),
                baseOrientation=quaternion_xyzw(T_body[:3, :3]).tolist(),
                physicsClientId=client,
            )
            pb.changeDynamics(
                body,
                -1,
                lateralFriction=settings.friction,
                restitution=0.0,
                linearDamping=0.1,
                angularDamping=0.1,
                physicsClientId=client,
            )
            bodies.append(body)
        steps = int(settings.max_time_s / TIME_STEP_S)
        for step in range(steps):
            pb.stepSimulation(physicsClientId=client)
            if step % 24 == 23 and step > 120:
                speeds = [np.linalg.norm(pb.getBaseVelocity(b, physicsClientId=client)[0]) / SCALE for b in bodies]
                if max(speeds) < REST_SPEED_M_S:
                    break
        out = np.empty_like(T_bin_from_model)
        for i, b in enumerate(bodies):
            position, q = pb.getBasePositionAndOrientation(b, physicsClientId=client)
            R = np.asarray(pb.getMatrixFromQuaternion(q, physicsClientId=client)).reshape(3, 3)
            out[i] = make_T(R, np.asarray(position) / SCALE) @ invert_T(T_model_from_body[kinds[i]])
    finally:
        pb.disconnect(client)
    centre = np.stack([centres[j] for j in kinds])
    middles = np.einsum("kij,kj->ki", out[:, :3, :3], centre) + out[:, :3, 3]
    inside = np.all(np.abs(middles[:, :2]) < np.asarray(inner_half_xy_m), axis=1) & (middles[:, 2] > 0.0)
    return out, inside


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()  # scipy's order is (x, y, z, w), as pybullet's
