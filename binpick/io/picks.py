"""Pick lists (`picks.json`): the ordered picks of one capture, in the camera frame and the robot's
base frame, and why the other parts have none. Spec: data/README.md#picks."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import write_text
from binpick.io.poses import PartPose
from binpick.picking.arm import WAYPOINTS, ArmMotion
from binpick.picking.plan import Pick, PickPlan
from binpick.robot.pose_formats import FIELDS, rounded, to_robot

FORMAT = "binpick-picks"
VERSION = 1


def _T(T: np.ndarray) -> list[list[float]]:
    return np.asarray(T, dtype=float).round(9).tolist()


def _tool_frame_fields(T_base_from_cam: np.ndarray | None, up_cam: np.ndarray, pose_format: str) -> dict:
    return {
        "unit": "m",
        "tool_frame": "origin at the tool centre point, z the approach, x the jaws' closing axis "
        "(binpick/picking/gripper.py)",
        "calibrated": T_base_from_cam is not None,
        "T_base_from_cam": _T(_base(T_base_from_cam)),
        "up_cam": [round(float(x), 9) for x in up_cam],
        "pose_format": pose_format,
        **({"pose_fields": list(FIELDS[pose_format])} if pose_format != "matrix" else {}),
    }


def _base(T_base_from_cam: np.ndarray | None) -> np.ndarray:
    return np.eye(4) if T_base_from_cam is None else np.asarray(T_base_from_cam, dtype=float)


def _pick_entry(
    rank: int, p: Pick, pose_index: int, gripper: str, T_base_from_cam: np.ndarray | None, pose_format: str
) -> dict:
    """One pick of picks.json: its pose, grasp, tool poses (camera, base), arm and robot poses."""
    T_base = _base(T_base_from_cam)
    cam = {"pregrasp": p.T_cam_from_pregrasp, "grasp": p.T_cam_from_grasp, "postgrasp": p.T_cam_from_postgrasp}
    entry = {
        "rank": rank,
        "pose_index": pose_index,
        "grasp_id": p.grasp_id,
        "score": round(p.score, 6),
        "clearance_m": round(p.clearance_m, 6),
        "height_m": round(p.height_m, 6),
        "trusted": p.trusted,
        "lifts_past": list(p.lifts_past),
        **({"width_m": round(p.width_m, 6)} if gripper == "jaw" else {}),
        "camera": {k: _T(v) for k, v in cam.items()},
        "base": {k: _T(T_base @ v) for k, v in cam.items()},
    }
    if p.arm is not None:
        motion: ArmMotion = p.arm
        entry["arm"] = {
            "joints_rad": {name: [round(float(x), 9) for x in motion.q[name]] for name in WAYPOINTS},
            "turn_deg": round(motion.turn_deg, 6),
            "place_tcp_base": _T(motion.T_base_from_place_tcp),
            "motion_s": round(motion.motion_s, 6),
            "path": list(motion.path),
            "carry_share": round(motion.carry_share, 6),
        }
    if pose_format != "matrix":
        robot = {k: rounded(to_robot(T_base @ v, pose_format), pose_format) for k, v in cam.items()}
        if p.arm is not None:
            robot["place"] = rounded(to_robot(p.arm.T_base_from_place_tcp, pose_format), pose_format)
        entry["robot"] = robot
    return entry


def picks_document(
    capture: str,
    part: str,
    gripper: str,
    plan: PickPlan,
    T_base_from_cam: np.ndarray | None,
    pose_format: str = "matrix",
) -> dict:
    """The picks.json content (the service answers with the same). With a robot pose_format (ur,
    abb, kuka, fanuc: binpick/robot/pose_formats.py) each pick also has `robot`: its base-frame
    tool poses in that controller's convention and units."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "capture": capture,
        "part": part,
        "gripper": gripper,
        **_tool_frame_fields(T_base_from_cam, plan.up_cam, pose_format),
        "picks": [
            _pick_entry(k, p, p.pose_index, gripper, T_base_from_cam, pose_format) for k, p in enumerate(plan.picks)
        ],
        "unpicked": [{"pose_index": i, "reason": reason} for i, reason in plan.unpicked],
        "counts": plan.counts(),
    }


def mixed_picks_document(
    capture: str,
    grippers: dict[str, str],
    n_poses: dict[str, int],
    picks: list[tuple[str, Pick]],
    unpicked: dict[str, list[tuple[int, str]]],
    conflicts: list[tuple[str, str]],
    up_cam: np.ndarray,
    T_base_from_cam: np.ndarray | None,
    pose_format: str = "matrix",
) -> dict:
    """The picks.json content of a capture of several kinds of part (binpick/scene/mixed.py):
    `parts` in their order (grippers: part -> its gripper; n_poses: part -> its kept poses, whose
    concatenation in that order `pose_index` counts in), one pick list, each pick and unpicked
    part naming its `part`, and `conflicts`: (the part whose pose lost a region, the part that
    kept it)."""
    offset, start = {}, 0
    for name in grippers:
        offset[name], start = start, start + n_poses.get(name, 0)
    gripper = next(iter(set(grippers.values()))) if len(set(grippers.values())) == 1 else "mixed"
    return {
        "format": FORMAT,
        "version": VERSION,
        "capture": capture,
        "parts": list(grippers),
        "gripper": gripper,
        **_tool_frame_fields(T_base_from_cam, up_cam, pose_format),
        "picks": [
            {
                "part": name,
                **_pick_entry(k, p, offset[name] + p.pose_index, grippers[name], T_base_from_cam, pose_format),
            }
            for k, (name, p) in enumerate(picks)
        ],
        "unpicked": [
            {"part": name, "pose_index": offset[name] + i, "reason": reason}
            for name, rows in unpicked.items()
            for i, reason in rows
        ],
        "conflicts": [{"part": lost, "kept_by": kept} for lost, kept in conflicts],
        "counts": {
            "n_parts": float(sum(n_poses.values())),
            "n_picks": float(len(picks)),
            "n_conflicts": float(len(conflicts)),
        },
    }


def pose_entries(posed: Sequence[tuple[str | None, PartPose]]) -> list[dict]:
    """An answer's `poses`: each (its part's name, None in a one-part answer; the pose), with the
    pose's T_cam_from_model and score."""
    return [
        {
            **({"part": name} if name is not None else {}),
            "T_cam_from_model": np.asarray(p.T_cam_from_model).round(9).tolist(),
            "score": round(p.score, 6),
        }
        for name, p in posed
    ]


def save_picks(
    path: str | Path,
    capture: str,
    part: str,
    gripper: str,
    plan: PickPlan,
    T_base_from_cam: np.ndarray | None,
    pose_format: str = "matrix",
) -> None:
    write_picks_document(path, picks_document(capture, part, gripper, plan, T_base_from_cam, pose_format))


def write_picks_document(path: str | Path, doc: dict) -> None:
    """Write a document picks_document made (the service keeps its answers with this)."""
    write_text(path, json.dumps(doc, indent=1) + "\n")


def load_picks(path: str | Path) -> dict:
    """The document as written (checked to be a pick list)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "pick list not found (run the pick stage first)")
    try:
        doc = json.loads(path.read_text())
    except ValueError as exc:
        raise InputError(path, f"not a JSON pick list ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("picks"), list):
        raise InputError(path, f'not a binpick pick list (expected "format": "{FORMAT}")')
    return doc
