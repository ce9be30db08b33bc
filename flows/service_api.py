"""The pick service's request and answer types, shared by HTTP and the TCP line protocol. FastAPI
publishes them as the service's OpenAPI schema (`/openapi.json`, rendered at `/docs`), the
contract a robot integrator programs against. The answer is the picks.json document of the batch
pipeline (binpick.io.picks, data/README.md) plus the request's id, timings and poses."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from binpick.io.mesh import METRES_PER_UNIT
from binpick.robot.pose_formats import PoseFormat

Matrix4 = list[list[float]]


class PicksRequest(BaseModel):
    """Picks for one capture: an upload (HTTP body with `format` as a query parameter, or
    `data_b64` on the line protocol), a capture file on the service's machine (`path`, inside the
    project or service.capture_folders) or a frame from the connected Zivid camera (`camera`)."""

    model_config = ConfigDict(extra="forbid")

    part: str | None = Field(None, description="a part the service serves (GET /health lists them)")
    parts: list[str] | None = Field(
        None,
        description="instead of part: several parts in one bin (a mixed bin): each part's poses, conflicts between "
        "them resolved by verification, one pick list naming each pick's part; a comma-separated list as a query "
        "parameter",
    )
    priority: list[str] | None = Field(
        None,
        description="a mixed bin: these parts are picked first, in this order (the rest by pick.order); default: "
        "pick.part_priority",
    )
    quota: dict[str, int] | None = Field(
        None,
        description="a mixed bin: at most this many picks of a part in the answer (what the kit still needs of it; "
        "0: none, its poses stay obstacles); as a query parameter part:count pairs, e.g. ring_screw:2,gear_shaft:0; "
        "default: pick.part_quota",
    )
    path: str | None = Field(
        None, description="capture file on the service's machine, absolute or relative to the project"
    )
    camera: bool = Field(False, description="grab a frame from the connected Zivid camera")
    unit: str = Field("mm", description="unit of the capture's coordinates: mm, m or in")
    format: str | None = Field(None, description="an upload's file format: ply, pcd, zdf, csv, xyz, png")
    pose_format: PoseFormat | None = Field(
        None,
        description="also give each pick's base-frame tool poses as this robot wants them (`robot` in each pick): "
        "ur p[x, y, z, rx, ry, rz] in m and rad; abb [x, y, z, q1..q4] in mm, quaternion w first; kuka X Y Z A B C "
        "in mm and deg; fanuc X Y Z W P R in mm and deg; matrix: only the 4 x 4 matrices. Default: pick.pose_format",
    )
    failed_grasps: list[list[float]] | None = Field(
        None,
        description="where the gripper failed to hold a part in earlier picks (no vacuum, jaws closed on air): each "
        "such pick's tool centre point, camera frame, metres (the translation of its camera grasp pose, "
        "picks[i].camera.grasp, column 3). No grasp within the gripper's contact size of one (the suction cup's "
        "lip, a jaw finger's width) is offered; as a query parameter x,y,z triples joined by ';'",
    )
    data_b64: str | None = Field(None, description="line protocol: the uploaded capture, base64")
    token: str | None = Field(
        None, description="line protocol: the token, when the service requires one (HTTP: Authorization: Bearer)"
    )

    @field_validator("parts", "priority", mode="before")
    @classmethod
    def _listed(cls, value: object) -> object:
        return [v.strip() for v in value.split(",") if v.strip()] if isinstance(value, str) else value

    @field_validator("quota", mode="before")
    @classmethod
    def _counted(cls, value: object) -> object:
        if not isinstance(value, str):
            return value
        pairs = [v.strip().split(":") for v in value.split(",") if v.strip()]
        if any(len(pair) != 2 or not pair[1].strip().isdigit() for pair in pairs):
            raise ValueError(f"quota {value!r}: expected part:count pairs, e.g. ring_screw:2,gear_shaft:0")
        return {name.strip(): int(count) for name, count in pairs}

    @field_validator("failed_grasps", mode="before")
    @classmethod
    def _points(cls, value: object) -> object:
        if isinstance(value, str):
            try:
                value = [[float(x) for x in triple.split(",")] for triple in value.split(";") if triple.strip()]
            except ValueError:
                raise ValueError(f"failed_grasps {value!r}: expected x,y,z triples joined by ';'") from None
        return value

    @field_validator("failed_grasps")
    @classmethod
    def _xyz(cls, value: list[list[float]] | None) -> list[list[float]] | None:
        if value is not None and any(len(p) != 3 or not all(math.isfinite(x) for x in p) for p in value):
            raise ValueError("failed_grasps: each point is three finite numbers x, y, z (metres, camera frame)")
        return value

    @model_validator(mode="after")
    def _one_or_several(self) -> PicksRequest:
        if (self.part is None) == (self.parts is None):
            raise ValueError('a request names its "part", or its "parts" for a mixed bin (not both)')
        if self.parts is not None and not self.parts:
            raise ValueError('"parts" names at least one part')
        if self.quota is not None and any(n < 0 for n in self.quota.values()):
            raise ValueError('"quota" counts picks: 0 or more')
        return self

    @field_validator("unit")
    @classmethod
    def _known_unit(cls, unit: str) -> str:
        if unit not in METRES_PER_UNIT:
            raise ValueError(f"unit {unit!r} is not one of {', '.join(METRES_PER_UNIT)}")
        return unit


class PosesOfPick(BaseModel):
    pregrasp: Matrix4
    grasp: Matrix4
    postgrasp: Matrix4


class ArmJoints(BaseModel):
    pregrasp_above: list[float] = Field(
        description="the pre-grasp pose raised by cell.lift_m (an approach that does not go straight to the pre-grasp "
        "comes down from it)"
    )
    lift: list[float] = Field(
        description="the post-grasp pose raised by cell.lift_m, reached from the post-grasp along the tool's straight "
        "line up (a linear move, e.g. UR moveL)"
    )
    pregrasp: list[float]
    grasp: list[float]
    postgrasp: list[float]
    place_above: list[float] = Field(description="cell.place.above_m above the place")
    place: list[float]


class ArmOfPick(BaseModel):
    joints_rad: ArmJoints = Field(
        description="the arm's joint angles (base, shoulder, elbow, wrist 1, 2, 3) at each waypoint; the pick moves "
        "from the start through pregrasp (or pregrasp_above, pregrasp), grasp, postgrasp, lift, place_above, place in "
        "straight joint lines, but for postgrasp to lift: the tool's straight line up"
    )
    turn_deg: float = Field(
        description="the tool turned about its axis from the grasp's own (the poses above include it)"
    )
    place_tcp_base: Matrix4 = Field(description="T_base_from_tcp at the place")
    motion_s: float = Field(description="seconds of arm motion from the start to the place at cell.speed_scaling")
    path: list[str] = Field(description="the waypoints in the order the arm moves through them from where it starts")
    carry_share: float = Field(
        description="share of the joint speed (its square of the acceleration) from the grasp on, so that the gripper "
        "holds the part's weight and the motion's forces (1: full speed)"
    )


class RobotPoses(BaseModel):
    pregrasp: list[float]
    grasp: list[float]
    postgrasp: list[float]
    place: list[float] | None = Field(None, description="the place pose, when the arm's motion was planned")


class Pick(BaseModel):
    part: str | None = Field(None, description="a mixed bin: the part this pick takes")
    rank: int = Field(description="0 = pick this first")
    pose_index: int = Field(description="index into `poses`")
    grasp_id: str
    score: float
    clearance_m: float
    height_m: float
    trusted: bool = Field(description="the pose's verification left no doubt (seen-through share within the limit)")
    width_m: float | None = Field(None, description="jaw gripper: the opening at the grasp")
    camera: PosesOfPick = Field(description="T_cam_from_tool of the pre-grasp, grasp and post-grasp poses (metres)")
    base: PosesOfPick = Field(description="the same in the robot base frame (T_base_from_cam applied)")
    arm: ArmOfPick | None = Field(None, description="the arm's motion, when cell.arm is set and the camera calibrated")
    robot: RobotPoses | None = Field(
        None, description="the base-frame tool poses in the requested robot convention (`pose_fields` says the numbers)"
    )


class Unpicked(BaseModel):
    part: str | None = None
    pose_index: int
    reason: str


class Conflict(BaseModel):
    part: str = Field(description="the part whose pose lost the region")
    kept_by: str = Field(description="the part whose pose kept it")


class PoseOut(BaseModel):
    part: str | None = None
    T_cam_from_model: Matrix4
    score: float


class PicksAnswer(BaseModel):
    format: Literal["binpick-picks"]
    version: int
    capture: str = Field(description="the request's id")
    part: str | None = None
    parts: list[str] | None = Field(None, description="a mixed bin: its parts (pose_index counts their poses in order)")
    gripper: str
    unit: Literal["m"]
    tool_frame: str
    calibrated: bool = Field(description="T_base_from_cam is the hand-eye calibration (false: identity)")
    T_base_from_cam: Matrix4
    up_cam: list[float] = Field(description="the bin's up axis in the camera frame")
    pose_format: str = Field(description="matrix, ur, abb, kuka or fanuc (see PicksRequest.pose_format)")
    pose_fields: list[str] | None = Field(None, description="what each number of a pick's `robot` poses is")
    picks: list[Pick]
    unpicked: list[Unpicked]
    counts: dict[str, float]
    conflicts: list[Conflict] | None = Field(
        None,
        description="a mixed bin: each pose that lost its region to a pose of another part that explains more "
        "of the capture",
    )
    request_id: str
    timings_s: dict[str, float]
    poses: list[PoseOut]


class Health(BaseModel):
    status: Literal["ok"]
    parts: list[str]
    not_served: dict[str, str] = Field(description="parts of the project not served, and why")
    answered: int
    waiting: int
    uptime_s: float


class ErrorAnswer(BaseModel):
    error: str = Field(description="one line; names no path of the service's machine but the client's own")
    status: int | None = Field(None, description="line protocol: the HTTP status it stands for")


def validation_message(exc: ValidationError) -> str:
    """One line from pydantic's errors: `field: what is wrong`."""
    return "; ".join(
        f"{'.'.join(str(x) for x in e['loc']) or 'request'}: {str(e['msg']).removeprefix('Value error, ')}"
        for e in exc.errors()
    )
