"""The robot arm: kinematics, joint limits and link geometry from the URDF a maintained package
ships (airo-models: the Universal Robots UR5e and UR3e; example-robot-data: the UR10), inverse
kinematics from an analytic solver (ur_analytic_ik). Nothing is downloaded.

Frames: `base` is the controller's base frame (the one a UR teach pendant and `getActualTCPPose`
use; the URDF's REP-103 `base_link` is it turned half a turn about z), `flange` the tool flange
(URDF `tool0`: z out of the flange). Joint angles in radians, lengths in metres.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import trimesh

from binpick.log import loggers_raised
from binpick.native import stdout_silenced

log = logging.getLogger(__name__)

# The arms whose URDF a package ships and whose analytic IK ur_analytic_ik has: the e-series from
# airo-models, the UR10 (CB3, 1.3 m reach) from example-robot-data's ur_description.
ARMS = ("ur5e", "ur3e", "ur10")
EXAMPLE_ROBOT_DATA_URDF = {"ur10": "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur10_robot.urdf"}
# Joint acceleration where a URDF declares none (example-robot-data's): the 2.5 rad/s^2 that
# airo-models declares for every joint of the e-series arms; Universal Robots publishes no figure.
DEFAULT_ACCELERATION_RAD_S2 = 2.5
BASE, FLANGE = "base", "tool0"
# Link surfaces are sampled about this far apart for collision checks: a check's radius adds
# half of it, so that nothing slips between the samples.
LINK_SAMPLE_SPACING_M = 0.025
# The URDF files declare joint accelerations in Drake's namespace on <limit>.
ACCELERATION_ATTRIBUTE = "drake:acceleration"


@dataclass(frozen=True)
class ArmModel:
    """A six-axis arm.

    lower_rad, upper_rad, max_velocity_rad_s, max_acceleration_rad_s2 : (6,) per joint
    link_names : the links with collision geometry, base to flange
    link_points_m : per link (k_i, 3) its collision surface sampled every LINK_SAMPLE_SPACING_M,
                    link frame
    upper_arm_m, forearm_m : a UR's a2 and a3 (the upper arm's and the forearm's lengths,
                    negative in UR's convention)
    """

    name: str
    joint_names: tuple[str, ...]
    lower_rad: np.ndarray
    upper_rad: np.ndarray
    max_velocity_rad_s: np.ndarray
    max_acceleration_rad_s2: np.ndarray
    link_names: tuple[str, ...]
    link_points_m: tuple[np.ndarray, ...]
    upper_arm_m: float
    forearm_m: float
    urdf_path: Path
    # The URDF's chain from the base frame: per joint its origin (4, 4), its axis (3,) and the index
    # of its angle in q (-1: fixed), and the link it leads to.
    _chain: tuple[tuple[np.ndarray, np.ndarray, int, str], ...] = field(repr=False, compare=False)
    _ik: ModuleType = field(repr=False, compare=False)

    def flange_pose(self, q: np.ndarray) -> np.ndarray:
        """T_base_from_flange (4, 4) at joint angles q (6,)."""
        return np.asarray(self._ik.forward_kinematics(*np.asarray(q, dtype=float)), dtype=float)

    def ik(self, T_base_from_flange: np.ndarray) -> np.ndarray:
        """(m, 6) the analytic solutions (m <= 8), each joint wrapped to (-pi, pi]; none when the
        pose is out of reach. Other turns of a joint by 2 pi: robot.configuration.nearest_turns."""
        T = np.ascontiguousarray(np.asarray(T_base_from_flange, dtype=np.float64))
        with stdout_silenced():
            solutions = [np.asarray(s, dtype=float) for s in self._ik.inverse_kinematics(T)]
        q = np.array([s for s in solutions if np.all(np.isfinite(s))]).reshape(-1, 6)
        return np.angle(np.exp(1j * q))

    def link_transforms(self, q: np.ndarray) -> np.ndarray:
        """(N, L, 4, 4) T_base_from_link of link_names at N configurations q (N, 6), by the URDF's
        joint chain (batched: a path's hundreds of configurations in one pass, where a URDF
        library's per-configuration update takes milliseconds each)."""
        out = self._chain_transforms(q)
        return np.stack([out[name] for name in self.link_names], axis=1)

    def flange_poses(self, q: np.ndarray) -> np.ndarray:
        """(N, 4, 4) T_base_from_flange at N configurations q (N, 6) (batched flange_pose)."""
        return self._chain_transforms(q)[FLANGE]

    def _chain_transforms(self, q: np.ndarray) -> dict[str, np.ndarray]:
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        out: dict[str, np.ndarray] = {}
        for origin, axis, j, child in self._chain:
            T = T @ origin
            if j >= 0:
                T = T @ _rotations(axis, q[:, j])
            out[child] = T
        return out

    def surface_points(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The arm's sampled surface at N configurations q (N, 6): (N, n, 3) base frame and (n,)
        the link index of each point."""
        Ts = self.link_transforms(q)
        points = [
            np.matmul(pts[None], Ts[:, k, :3, :3].transpose(0, 2, 1)) + Ts[:, k, None, :3, 3]
            for k, pts in enumerate(self.link_points_m)
        ]
        index = np.concatenate([np.full(len(p), k) for k, p in enumerate(self.link_points_m)])
        return np.concatenate(points, axis=1), index


def _rotations(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 4, 4) turns by angles (N,) about the unit axis (3,) (Rodrigues)."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    R = np.eye(4)[None].repeat(len(angles), axis=0)
    R[:, :3, :3] = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    return R


def load_arm(name: str) -> ArmModel:
    """The arm `name` (one of ARMS), loaded once per process."""
    if name not in ARMS:
        raise ValueError(f"unknown arm {name!r}; known: {', '.join(ARMS)}")
    return _load(name)


def _urdf_path(name: str) -> Path:
    if name in EXAMPLE_ROBOT_DATA_URDF:
        from importlib.metadata import PackageNotFoundError, distribution

        try:
            return Path(str(distribution("example-robot-data").locate_file(EXAMPLE_ROBOT_DATA_URDF[name])))
        except PackageNotFoundError:
            raise ValueError(f"the {name} model needs example-robot-data: pip install example-robot-data") from None
    import airo_models

    return Path(airo_models.get_urdf_path(name))


@functools.lru_cache(maxsize=len(ARMS))
def _load(name: str) -> ArmModel:
    import ur_analytic_ik
    import yourdfpy

    path = _urdf_path(name)
    # yourdfpy logs the Drake namespace of the acceleration limits as an error and reads on.
    with loggers_raised(("yourdfpy",), logging.CRITICAL):
        urdf = yourdfpy.URDF.load(str(path), load_meshes=False, load_collision_meshes=False)
    joints = tuple(urdf.actuated_joint_names)
    limits = [urdf.joint_map[j].limit for j in joints]
    accelerations = _acceleration_limits(path, joints)
    chain_links = _chain_links(urdf)
    links = tuple(name for name in chain_links if urdf.link_map[name].collisions)
    points = tuple(_link_surface(urdf, path.parent, name) for name in links)
    return ArmModel(
        name=name,
        joint_names=joints,
        lower_rad=np.array([lim.lower for lim in limits], dtype=float),
        upper_rad=np.array([lim.upper for lim in limits], dtype=float),
        max_velocity_rad_s=np.array([lim.velocity for lim in limits], dtype=float),
        max_acceleration_rad_s2=accelerations,
        link_names=links,
        link_points_m=points,
        upper_arm_m=_link_length(urdf, "elbow_joint"),
        forearm_m=_link_length(urdf, "wrist_1_joint"),
        urdf_path=path,
        _chain=_joint_chain(urdf, chain_links, joints),
        _ik=getattr(ur_analytic_ik, name),
    )


def _link_length(urdf: Any, joint: str) -> float:
    """A UR link's length from the joint at its end (negative, UR's convention): the largest offset
    of the joint's origin (along x in airo-models' files, z in ur_description's; the others are
    the small sideways offsets)."""
    return -float(np.max(np.abs(np.asarray(urdf.joint_map[joint].origin, dtype=float)[:3, 3])))


def _chain_links(urdf: Any) -> list[str]:
    """The links from the root to the flange, in chain order."""
    parent = {j.child: j.parent for j in urdf.robot.joints}
    chain, link = [FLANGE], FLANGE
    while link in parent:
        link = parent[link]
        chain.append(link)
    return chain[::-1]


def _joint_chain(urdf: Any, chain_links: list[str], joints: tuple[str, ...]) -> tuple:
    """The joints from the base frame along the chain (origin, axis, angle index, child link); the
    base frame hangs off the chain's root by a fixed joint, undone first."""
    by_child = {j.child: j for j in urdf.robot.joints}
    base_joint = by_child[BASE]
    steps: list[tuple[np.ndarray, np.ndarray, int, str]] = [
        (np.linalg.inv(np.asarray(base_joint.origin, dtype=float)), np.zeros(3), -1, chain_links[0])
    ]
    for link in chain_links[1:]:
        joint = by_child[link]
        moving = joint.type in ("revolute", "continuous")
        axis = np.asarray(joint.axis if joint.axis is not None else (0.0, 0.0, 1.0), dtype=float)
        origin = np.asarray(joint.origin if joint.origin is not None else np.eye(4), dtype=float)
        steps.append((origin, axis / np.linalg.norm(axis), joints.index(joint.name) if moving else -1, link))
    return tuple(steps)


def _acceleration_limits(path: Path, joints: tuple[str, ...]) -> np.ndarray:
    """(6,) rad/s^2 from the URDF's <limit drake:acceleration=...>; the prefix is not declared in
    the file, so it is read with a recovering parser."""
    import lxml.etree as ET

    root = ET.parse(str(path), ET.XMLParser(recover=True)).getroot()
    found = {}
    for joint in root.iter("joint"):
        limit = joint.find("limit")
        if limit is not None and limit.get(ACCELERATION_ATTRIBUTE) is not None:
            found[joint.get("name")] = float(limit.get(ACCELERATION_ATTRIBUTE))
    if not found:  # none declared at all (example-robot-data)
        return np.full(len(joints), DEFAULT_ACCELERATION_RAD_S2)
    missing = [j for j in joints if j not in found]
    if missing:
        raise ValueError(f"{path}: no acceleration limit for {', '.join(missing)}")
    return np.array([found[j] for j in joints], dtype=float)


def _link_surface(urdf: Any, folder: Path, link: str) -> np.ndarray:
    """(k, 3) the link's collision geometry (meshes and spheres) sampled evenly, link frame."""
    parts = []
    for c in urdf.link_map[link].collisions:
        g = c.geometry
        if g.mesh is not None:
            mesh = trimesh.load(_mesh_path(folder, g.mesh.filename), force="mesh")
            assert isinstance(mesh, trimesh.Trimesh)  # force="mesh" merges a scene into one
            if g.mesh.scale is not None:
                mesh.apply_scale(g.mesh.scale)
        elif g.sphere is not None:
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=g.sphere.radius)
        elif g.cylinder is not None:
            mesh = trimesh.creation.cylinder(radius=g.cylinder.radius, height=g.cylinder.length)
        elif g.box is not None:
            mesh = trimesh.creation.box(extents=g.box.size)
        else:
            continue
        if c.origin is not None:
            mesh.apply_transform(c.origin)
        count = max(16, int(mesh.area / LINK_SAMPLE_SPACING_M**2))
        # A fixed seed: the same arm is the same sample in every process. A link's thin parts
        # take fewer than count at the spacing, which trimesh logs as a warning: enough as they are.
        with loggers_raised(("trimesh",), logging.ERROR):
            points, _ = trimesh.sample.sample_surface_even(mesh, count, seed=0)
        parts.append(np.asarray(points, dtype=float))
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def _mesh_path(folder: Path, filename: str) -> Path:
    """A URDF's mesh file: relative to its folder, or package://<package>/<path> inside the
    nearest folder above it named <package> (example-robot-data's layout)."""
    if not filename.startswith("package://"):
        return folder / filename
    package, _, rest = filename[len("package://") :].partition("/")
    for above in (folder, *folder.parents):
        if above.name == package:
            return above / rest
    raise ValueError(f"{folder}: no folder {package!r} above it for {filename}")
