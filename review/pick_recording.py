"""rerun recordings of grasps and picks: the gripper drawn at its poses. Apart from the scene
recordings (recording.py), so that what draws a scene does not depend on the gripper's code."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from binpick.io.atomic import atomic_path
from binpick.io.cloud import CleanCloud
from binpick.io.part_model import PartModel
from binpick.io.poses import PartPose
from binpick.palette import instance_colours
from binpick.picking.gripper import gripper_primitives
from review.recording import log_part

GRIPPER_COLOUR = np.array([230, 160, 40, 140], np.uint8)
REJECTED_COLOUR = np.array([220, 50, 50, 255], np.uint8)
GRASP_COLOURS = {"suction": np.array([40, 140, 230], np.uint8), "jaw": np.array([230, 120, 40], np.uint8)}
# Grippers drawn at this many first picks.
DRAWN_PICKS = 3


def _gripper_mesh(primitives: list, T_cam_from_tool: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the gripper's boxes and cylinders at a pose (for drawing)."""
    import trimesh

    meshes = []
    for prim in primitives:
        if hasattr(prim, "lo"):
            m = trimesh.creation.box(extents=prim.hi - prim.lo)
            m.apply_translation((prim.lo + prim.hi) / 2.0)
        else:
            m = trimesh.creation.cylinder(radius=prim.radius, height=prim.z1 - prim.z0, sections=24)
            m.apply_translation([0.0, 0.0, (prim.z0 + prim.z1) / 2.0])
        m.apply_transform(T_cam_from_tool)
        meshes.append(m)
    whole: trimesh.Trimesh = trimesh.util.concatenate(meshes)  # type: ignore[assignment]  # a list of meshes gives a mesh
    return np.asarray(whole.vertices, np.float32), np.asarray(whole.faces, np.uint32)


def _grasp_arrows(T_frame_from_tool: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Arrows ending at each grasp's tool centre point, along its approach."""
    T = np.asarray(T_frame_from_tool).reshape(-1, 4, 4)
    vectors = T[:, :3, 2] * length_m
    return (T[:, :3, 3] - vectors).astype(np.float32), vectors.astype(np.float32)


def write_grasp_recording(path: Path, part: PartModel, sets: dict, params) -> None:
    """The part's mesh with its grasps: suction approaches as arrows, jaw grasps as arrows and
    the line between their contacts; the gripper drawn at the best grasp of each kind."""
    import rerun as rr

    rec = rr.RecordingStream("binpick", recording_id=f"grasps-{part.name}")
    length = 0.25 * part.diameter_m
    with atomic_path(path) as tmp:
        rec.save(str(tmp))
        rec.log(
            "model/mesh",
            rr.Mesh3D(
                vertex_positions=part.mesh_vertices_m.astype(np.float32),
                triangle_indices=part.mesh_faces.astype(np.uint32),
                albedo_factor=np.array([200, 200, 200, 255], np.uint8),
            ),
            static=True,
        )
        for kind, grasps in sets.items():
            if len(grasps) == 0:
                continue
            origins, vectors = _grasp_arrows(grasps.T_model_from_tool, length)
            rec.log(
                f"model/grasps/{kind}",
                rr.Arrows3D(origins=origins, vectors=vectors, colors=GRASP_COLOURS[kind], labels=grasps.ids),
                static=True,
            )
            if kind == "jaw":
                T = grasps.T_model_from_tool
                half = T[:, :3, 0] * grasps.width_m[:, None] / 2.0
                strips = np.stack([T[:, :3, 3] - half, T[:, :3, 3] + half], axis=1).astype(np.float32)
                rec.log("model/grasps/jaw_contacts", rr.LineStrips3D(strips, colors=GRASP_COLOURS[kind]), static=True)
            vertices, faces = _gripper_mesh(
                gripper_primitives(params, kind, float(grasps.width_m[0])), grasps.T_model_from_tool[0]
            )
            rec.log(
                f"model/gripper/{kind}",
                rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces, albedo_factor=GRIPPER_COLOUR),
                static=True,
            )
        rec.log(
            "model/summary", rr.TextDocument("\n".join(f"{k}: {len(g)} grasps" for k, g in sets.items())), static=True
        )
        rec.flush()
        rec.disconnect()


def write_pick_recording(
    path: Path,
    name: str,
    cloud: CleanCloud,
    part: PartModel,
    estimates: list[PartPose],
    plan,
    kind: str,
    params,
    stream=None,
) -> None:
    """The scene with the parts at their poses, the gripper at the first picks (pre-grasp
    arrow to grasp), the order as labels, and the refused grasps in their own entity. stream: a
    RecordingStream to reuse (a resident process writing many recordings: each new stream keeps
    two threads alive); it is pointed at this file and left open."""
    import rerun as rr

    rec = stream if stream is not None else rr.RecordingStream("binpick", recording_id=f"picks-{name}")
    with atomic_path(path) as tmp:
        rec.save(str(tmp))
        if stream is not None:
            rec.send_recording_name(f"picks-{name}")
        rec.log("camera", rr.ViewCoordinates.RDF, static=True)
        rec.log("camera/scene", rr.Points3D(cloud.points_m, colors=cloud.rgb, radii=0.0008), static=True)
        palette = instance_colours(max(len(estimates), 1))
        for k, pose in enumerate(estimates):
            log_part(rec, f"camera/parts/{k}", pose, part, np.append(palette[k % len(palette)], 255).astype(np.uint8))
        for rank, p in enumerate(plan.picks[:DRAWN_PICKS]):
            vertices, faces = _gripper_mesh(gripper_primitives(params, kind, p.width_m), p.T_cam_from_grasp)
            rec.log(
                f"camera/picks/{rank}/gripper",
                rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces, albedo_factor=GRIPPER_COLOUR),
                static=True,
            )
        if plan.picks:
            T = np.array([p.T_cam_from_grasp for p in plan.picks])
            pre = np.array([p.T_cam_from_pregrasp[:3, 3] for p in plan.picks], np.float32)
            rec.log(
                "camera/picks/approach",
                rr.Arrows3D(
                    origins=pre,
                    vectors=(T[:, :3, 3] - pre).astype(np.float32),
                    labels=[f"#{k} part {p.pose_index} {p.grasp_id}" for k, p in enumerate(plan.picks)],
                ),
                static=True,
            )
        if plan.rejected:
            origins, vectors = _grasp_arrows(np.array([r.T_cam_from_grasp for r in plan.rejected]), 0.01)
            rec.log(
                "camera/rejected",
                rr.Arrows3D(
                    origins=origins,
                    vectors=vectors,
                    colors=REJECTED_COLOUR,
                    labels=[f"part {r.pose_index} {r.grasp_id}: {r.reason}" for r in plan.rejected],
                ),
                static=True,
            )
        lines = [
            f"#{k}: part {p.pose_index}, grasp {p.grasp_id}, score {p.score:.3f}, clearance "
            f"{1000 * p.clearance_m:.1f} mm"
            for k, p in enumerate(plan.picks)
        ]
        lines += [f"part {i}: {reason}" for i, reason in plan.unpicked]
        rec.log("picks", rr.TextDocument("\n".join(lines) or "no parts"), static=True)
        rec.flush()
        if stream is None:
            rec.disconnect()
