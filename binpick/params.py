"""Typed, validated settings from params.yaml.

params.yaml has one section per stage. Two layers override a section, in this order:
  1. the active profile: `profiles.<profile>.<section>` (every profile lists every section, `{}`
     when it changes nothing, so that DVC can track exactly the keys a stage uses);
  2. the part: `parts.<part>.<section>` for the per-part stages.
Lengths are in metres and angles in degrees, and the key names say so.

params.yaml is the one source of every setting's value: the section models below declare types,
bounds and meanings, and no defaults (a key missing from the file fails at load, naming it).
Only the entries of a part or a capture have defaults, for their optional keys.
"""

from __future__ import annotations

import copy
import difflib
import re
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from binpick.errors import InputError, ParamsError

# Sections a profile or a part may override. `tracking` and `orchestration` are deliberately
# absent: where runs are logged and how work is spread change no result, so DVC does not track them.
SECTIONS = (
    "ingest",
    "camera",
    "generate",
    "train",
    "evaluate",
    "import_capture",
    "segment",
    "register",
    "render_demo",
)
PER_PART_SECTIONS = (
    "ingest",
    "camera",
    "generate",
    "import_capture",
    "train",
    "evaluate",
    "segment",
    "register",
    "pick",
)


# Names and paths from this file reach DVC's command lines (dvc.yaml interpolates them into shell
# commands), so they are held to a character set the shell gives no meaning to.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")
# Spaces are allowed inside a path (CAD exports have them; DVC's commands single-quote paths),
# not at its ends.
PATH_PATTERN = re.compile(r"[A-Za-z0-9_](?:[A-Za-z0-9_ ./-]{0,253}[A-Za-z0-9_./-])?")
NAME_RULE = "1-64 letters, digits, '_' or '-', starting with a letter or digit"
PATH_RULE = "a relative path inside the project of letters, digits, spaces, '_', '-', '.' and '/'"


def check_name(name: str, what: str) -> str:
    """`name` if it is a valid part, capture or profile name; ValueError naming `what` otherwise."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"{what} name {name!r} is not {NAME_RULE}")
    return name


def check_project_path(path: str, what: str) -> str:
    """`path` if it is a safe relative path inside the project; ValueError naming `what` otherwise.

    Only the text is checked here; `binpick.project` also resolves links against the project root.
    """
    if not isinstance(path, str) or not PATH_PATTERN.fullmatch(path) or ".." in PurePosixPath(path).parts:
        raise ValueError(f"{what} {path!r} is not {PATH_RULE} (no '..')")
    return path


# An explicit cell.T_flange_from_tcp puts the flange within this of where the modelled gripper ends.
TOOL_MOUNT_TOLERANCE_M = 0.001
GRIPPER_LENGTH_KEYS = {
    "suction": "pick.suction.cup_length_m + tool_length_m",
    "jaw": "pick.jaw.finger_length_m - pad_length_m / 2 + palm_depth_m + tool_length_m",
}


class _Strict(BaseModel):
    # populate_by_name: the `register` section is the attribute `registration`, because
    # `register` is taken by Python's ABC machinery on every pydantic model.
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class SymmetryParams(_Strict):
    """Proper rotational symmetry of a part, in the model frame of its CAD file."""

    kind: Literal["none", "n_fold", "revolution"] = "none"
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    order: int = Field(1, ge=1, description="n of an n-fold symmetry (rotations by 360/n deg)")
    # A point on the symmetry axis, model frame, metres. The axis passes through it.
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # A second, two-fold axis through origin_m, perpendicular to `axis`, for parts whose two faces
    # are alike (a nut, a washer): the group is then dihedral. null = none.
    flip_axis: tuple[float, float, float] | None = None

    @model_validator(mode="after")
    def _check(self) -> SymmetryParams:
        if self.kind == "n_fold" and self.order < 2:
            raise ValueError("an n_fold symmetry needs order >= 2")
        if sum(a * a for a in self.axis) < 1e-12:
            raise ValueError("symmetry axis must not be zero")
        if self.flip_axis is not None:
            a, f = np.asarray(self.axis, float), np.asarray(self.flip_axis, float)
            if np.linalg.norm(f) < 1e-12 or abs(a @ f) > 1e-6 * np.linalg.norm(a) * np.linalg.norm(f):
                raise ValueError("flip_axis must be non-zero and perpendicular to axis")
            if self.kind == "none":
                raise ValueError("flip_axis needs kind n_fold or revolution")
        return self


# Aluminium: a part whose material is not given weighs this much per cubic metre of its mesh.
DEFAULT_DENSITY_KG_M3 = 2700.0


class PartParams(_Strict):
    """One part: its CAD file, the unit of that file and its symmetry, plus section overrides."""

    mesh: str
    unit: Literal["mm", "m", "in", "auto"] = "auto"
    symmetry: SymmetryParams = SymmetryParams()
    ingest: dict[str, Any] = {}
    # A large part needs a larger bin, a camera farther away and a coarser voxel grid; the
    # part's captures are imported with its import_capture, so training and inference views match.
    camera: dict[str, Any] = {}
    generate: dict[str, Any] = {}
    import_capture: dict[str, Any] = {}
    train: dict[str, Any] = {}
    evaluate: dict[str, Any] = {}
    segment: dict[str, Any] = {}
    registration: dict[str, Any] = Field({}, alias="register")
    pick: dict[str, Any] = {}
    density_kg_m3: float = Field(
        DEFAULT_DENSITY_KG_M3, gt=0, description="the part's material (its weight on the gripper in bench cell)"
    )
    # A grasp file (data/README.md#grasps) with the part's pick points; '' = generated from the CAD model.
    grasps: str = ""
    # The part's finish, as the sensor models render it (generate.sensor.materials); null = the
    # generate.sensor.surface of the params.
    surface: Literal["matte", "machined", "shiny"] | None = None

    @field_validator("mesh")
    @classmethod
    def _safe_mesh(cls, mesh: str) -> str:
        return check_project_path(mesh, "mesh path")

    @field_validator("grasps")
    @classmethod
    def _safe_grasps(cls, grasps: str) -> str:
        return grasps if grasps == "" else check_project_path(grasps, "grasps path")


class CaptureParams(_Strict):
    """One capture file to process, and the part that is in it (`part`) or the parts of a mixed
    bin (`parts`, two or more: binpick/scene/mixed.py); `truth` optionally names a pose file with
    the ground truth of a one-part capture ('' when there is none, as for every real capture)."""

    file: str
    part: str = ""
    parts: list[str] = []
    unit: Literal["mm", "m", "in"] = "mm"
    truth: str = ""
    # Text captures: names of the columns (x, y, z, r, g, b, nx, ny, nz; others are ignored).
    columns: list[str] = ["x", "y", "z"]
    # Depth images: a JSON file with fx, fy, cx, cy in pixels ('' for other formats).
    intrinsics: str = ""
    # Overrides of the import_capture section for this capture's sensor (noisier sensors need wider
    # plane thresholds).
    import_capture: dict[str, Any] = {}

    @field_validator("file", "truth", "intrinsics")
    @classmethod
    def _safe_paths(cls, path: str, info: Any) -> str:
        return path if path == "" and info.field_name != "file" else check_project_path(path, f"{info.field_name} path")

    @field_validator("part")
    @classmethod
    def _safe_part(cls, part: str) -> str:
        return check_name(part, "part") if part else part

    @field_validator("parts")
    @classmethod
    def _safe_parts(cls, parts: list[str]) -> list[str]:
        return [check_name(p, "part") for p in parts]

    @model_validator(mode="after")
    def _one_part_or_a_mix(self) -> CaptureParams:
        if bool(self.part) == bool(self.parts):
            raise ValueError("a capture names its `part`, or the `parts` of a mixed bin, not both and not neither")
        if self.parts and (len(self.parts) < 2 or len(set(self.parts)) < len(self.parts)):
            raise ValueError(f"`parts` names two or more different parts, got {self.parts}")
        if self.parts and self.truth:
            raise ValueError("a mixed capture (`parts`) takes no `truth` file")
        return self

    @property
    def part_names(self) -> list[str]:
        """The parts in the capture: [part], or the parts of the mix in their order."""
        return list(self.parts) if self.parts else [self.part]


class IngestParams(_Strict):
    n_surface_points: int = Field(ge=100, description="dense surface sample of the part model")
    # Larger CAD meshes are decimated to this many faces (the diameter is taken before).
    max_faces: int = Field(ge=100)
    # Sizes outside these bounds are almost certainly a wrong unit.
    min_extent_m: float = Field(gt=0)
    max_extent_m: float = Field(gt=0)


class CameraParams(_Strict):
    """Pinhole camera looking straight down at the bin (OpenCV frame: x right, y down, z forward).

    params.yaml's values approximate a Zivid One+ Small (1920 x 1200) at 0.5 m.
    """

    width_px: int = Field(ge=16)
    height_px: int = Field(ge=16)
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    # Render at 1/downscale of the resolution (intrinsics scaled accordingly), for fast data sets.
    downscale: int = Field(ge=1)
    distance_m: float = Field(gt=0, description="camera centre above the bin floor")


class BinParams(_Strict):
    inner_x_m: float = Field(gt=0)
    inner_y_m: float = Field(gt=0)
    wall_height_m: float = Field(ge=0)
    wall_thickness_m: float = Field(gt=0)


class NoiseParams(_Strict):
    """Sensor model: depth noise along the ray grows with distance; grazing rays return nothing."""

    depth_sigma_m: float = Field(ge=0, description="noise std at zero range")
    depth_sigma_per_m2: float = Field(ge=0, description="added std per squared metre of range")
    max_incidence_deg: float = Field(gt=0, le=90)
    dropout_fraction: float = Field(ge=0, lt=1)


class SensorModelParams(_Strict):
    """One 3D sensor class (binpick/generation/sensor.py): its native image, the projector (or
    second camera) beside it, and the size of each effect; 0 (or false) turns an effect off."""

    width_px: int = Field(ge=16, description="native resolution; the principal point is the image centre")
    height_px: int = Field(ge=16)
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    working_distance_m: tuple[float, float] = Field(description="the maker's range; the camera is placed inside it")
    baseline_m: float = Field(ge=0, description="projector (or second camera) offset along the camera's +x")
    projector_angle_deg: float = Field(
        default=0.0, description="the projector's offset turned this far from +x about the optical axis (the mount)"
    )
    shadows: bool = Field(description="no data where the projector's ray to the surface is blocked")
    depth_sigma_m: float = Field(ge=0, description="range noise std at zero range, normal incidence")
    depth_sigma_per_m2: float = Field(ge=0, description="added std per squared metre of range")
    incidence_noise_gain: float = Field(ge=0, description="std times 1 + gain * a^2 / (90 deg - a)^2 at incidence a")
    dropout_start_deg: float = Field(ge=0, le=90, description="returns start to drop at this incidence ...")
    max_incidence_deg: float = Field(gt=0, le=90, description="... and all are gone beyond this one")
    dropout_fraction: float = Field(ge=0, lt=1, description="random dropout anywhere")
    mixed_pixel_share: float = Field(ge=0, le=1, description="share of depth-edge pixels that mix both depths")
    edge_jump_m: float = Field(gt=0, description="a depth step this large between neighbours is an edge")
    multipath_m: float = Field(ge=0, description="range bias at the bottom of a right-angled concave corner")
    multipath_radius_m: float = Field(gt=0, description="how far a facing surface reflects the projector onto a point")
    disparity_step_px: float = Field(ge=0, description="disparity quantisation (needs baseline_m); 0 = none")
    depth_step_m: float = Field(ge=0, description="range quantisation; 0 = none")

    @model_validator(mode="after")
    def _check(self) -> SensorModelParams:
        lo, hi = self.working_distance_m
        if not 0 < lo <= hi:
            raise ValueError(f"working_distance_m must be a range 0 < low <= high, got [{lo}, {hi}]")
        if self.dropout_start_deg > self.max_incidence_deg:
            raise ValueError("dropout_start_deg must not exceed max_incidence_deg")
        if self.disparity_step_px > 0 and self.baseline_m <= 0:
            raise ValueError("disparity_step_px needs a baseline_m above 0")
        return self


class MaterialParams(_Strict):
    """How a surface finish changes what a sensor returns from it."""

    noise_scale: float = Field(ge=0, description="range noise times this")
    max_incidence_deg: float = Field(gt=0, le=90, description="returns beyond this incidence are lost (steep metal)")
    specular_lobe_deg: float = Field(
        ge=0, lt=90, description="lost where the normal is this close to the projector-camera half vector"
    )
    dropout_fraction: float = Field(ge=0, lt=1, description="added random dropout on the surface")


SURFACES = ("matte", "machined", "shiny")


class SensorParams(_Strict):
    """Which sensor models generation draws from (one per scene) and their definitions.
    presets [] keeps the plain noise model (generate.noise) with the camera section's camera."""

    presets: list[str]
    effect_scale: tuple[float, float] = Field(
        description="each effect's size scaled by a factor drawn in this range per scene"
    )
    baseline_scale: tuple[float, float] = Field(
        description="the projector's baseline scaled by a factor drawn in this range per scene"
    )
    projector_angle_deg: tuple[float, float] = Field(
        description="the projector's side: its offset turned about the optical axis by an angle drawn in this range"
    )
    surface: Literal["matte", "machined", "shiny"] = Field(
        description="the part's finish (a part entry's `surface` sets it)"
    )
    models: dict[str, SensorModelParams]
    materials: dict[str, MaterialParams]

    @model_validator(mode="after")
    def _check(self) -> SensorParams:
        unknown = [n for n in self.presets if n not in self.models]
        if unknown:
            raise ValueError(f"sensor.presets names {unknown}, not in sensor.models (have: {sorted(self.models)})")
        if self.presets and sorted(self.materials) != sorted(SURFACES):
            raise ValueError(f"sensor.materials must define exactly {list(SURFACES)}")
        for name in ("effect_scale", "baseline_scale"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"sensor.{name} must be a range 0 < low <= high, got [{lo}, {hi}]")
        lo, hi = self.projector_angle_deg
        if not lo <= hi:
            raise ValueError(f"sensor.projector_angle_deg must be a range low <= high, got [{lo}, {hi}]")
        return self


class PlacementParams(_Strict):
    n_objects_min: int = Field(ge=1)
    n_objects_max: int = Field(ge=1)
    # mostly_lying: tilt about x/y drawn from a normal clipped to (0.25 pi, 0.75 pi).
    orientation: Literal["uniform", "mostly_lying"]
    heightmap_cell_m: float = Field(gt=0, description="grid of the drop-placement height maps")
    candidates_per_object: int = Field(ge=1, description="random poses tried; the lowest resting wins")
    max_pile_height_m: float = Field(gt=0, description="an object resting higher means the bin is full")
    # Start height of each object's lowest point above the bin floor: `pile` = resting on the pile
    # below; `u_shaped` = drawn from a U-shaped law (Beta(0.5, 0.5)) over [0, bin wall height];
    # `discrete` = one of height_levels_m. Never lower than the pile below. In `drop` mode objects
    # stay there (floating, as in the original work), in `physics` mode they fall from there.
    heights: Literal["pile", "u_shaped", "discrete"]
    height_levels_m: list[float] = Field(min_length=1)
    # drop: height-map drop placement (fast); physics: then settled by rigid-body simulation.
    mode: Literal["drop", "physics"]
    settle_max_s: float = Field(gt=0, description="physics: simulated time at most")
    max_penetration_m: float = Field(ge=0, description="physics: objects reaching deeper into another are removed")

    @model_validator(mode="after")
    def _check(self) -> PlacementParams:
        if self.n_objects_max < self.n_objects_min:
            raise ValueError("n_objects_max must be >= n_objects_min")
        return self


class ClutterParams(_Strict):
    """What real bins have and a clean render lacks, each drawn per scene: distractors (boxes,
    cylinders, thin plates, labelled -1) in and around the bin, other bin sizes and wall heights,
    a tilted camera at other heights, more or less sensor noise. All off: the plain scene."""

    n_distractors_max: int = Field(ge=0, description="0..n distractors per scene")
    distractor_size_rel: tuple[float, float] = Field(description="largest side, in part diameters")
    outside_share: float = Field(ge=0, le=1, description="share of distractors beside the bin, on the table")
    bin_scale: tuple[float, float] = Field(description="inner x and y scaled by a factor in this range")
    wall_height_scale: tuple[float, float]
    camera_tilt_deg_max: float = Field(ge=0, lt=60)
    camera_distance_scale: tuple[float, float]
    noise_scale: tuple[float, float] = Field(description="depth noise scaled by a factor in this range")
    # Other parts of a mixed bin dropped among the part's own instances (labelled -1, so that the
    # network learns to leave them alone); a part's own name in the list is skipped, so one list
    # in the shared section serves every part of the mix.
    parts: list[str] = []
    parts_share: float = Field(0.3, ge=0, le=1, description="share of a scene's dropped objects that are other parts")
    # A cell that gives its bin box (binpick fit-bin --apply) has its captures cropped to it: the
    # network sees a cloud with little but the parts left, unlike an uncropped view, and its
    # foreground head called far fewer part points a part's there (docs/benchmarks.md).
    box_share: float = Field(
        0.0, ge=0, le=1, description="share of scenes whose training view is cropped to the bin's inner box"
    )

    @field_validator("parts")
    @classmethod
    def _part_names(cls, parts: list[str]) -> list[str]:
        return [check_name(p, "part") for p in parts]

    @model_validator(mode="after")
    def _ranges(self) -> ClutterParams:
        for name in ("distractor_size_rel", "bin_scale", "wall_height_scale", "camera_distance_scale", "noise_scale"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"clutter.{name} must be a range 0 < low <= high, got [{lo}, {hi}]")
        return self

    def off(self) -> ClutterParams:
        """A copy that draws nothing: the plain scene."""
        return self.model_copy(
            update={
                "n_distractors_max": 0,
                "camera_tilt_deg_max": 0.0,
                "bin_scale": (1.0, 1.0),
                "wall_height_scale": (1.0, 1.0),
                "camera_distance_scale": (1.0, 1.0),
                "noise_scale": (1.0, 1.0),
                "parts": [],
                "box_share": 0.0,
            }
        )

    @property
    def active(self) -> bool:
        """Whether anything of the random variation is drawn (the other parts are not: see parts)."""
        return bool(self.n_distractors_max or self.camera_tilt_deg_max) or any(
            getattr(self, n) != (1.0, 1.0)
            for n in ("bin_scale", "wall_height_scale", "camera_distance_scale", "noise_scale")
        )


class GenerateParams(_Strict):
    n_train: int = Field(ge=1)
    n_val: int = Field(ge=1)
    n_test: int = Field(ge=1)
    placement: PlacementParams
    bin: BinParams
    noise: NoiseParams
    clutter: ClutterParams
    sensor: SensorParams


class TrainParams(_Strict):
    backbone: Literal["dgcnn", "pointnet"]
    k_neighbours: int = Field(ge=2)
    width: int = Field(ge=8, description="channels of the EdgeConv layers")
    embedding_dim: int = Field(ge=2)
    features: Literal["normals", "normalised_xyz"]
    n_points: int = Field(ge=64, description="points per training crop (nearest neighbours of a seed)")
    batch_size: int = Field(ge=1)
    epochs: int = Field(ge=1)
    learning_rate: float = Field(gt=0)
    weight_decay: float = Field(ge=0)
    patience_epochs: int = Field(ge=1, description="early stopping on the validation loss")
    # d_max of the paper; null = half the part diameter.
    d_max_m: float | None = Field(gt=0)
    centre_score_form: Literal["linear", "squared"]
    # Hinge margins in embedding space, 0 < eps1 < eps2 (no unit).
    eps1: float = Field(gt=0)
    eps2: float = Field(gt=0)
    centre_loss_weight: float = Field(ge=0)
    loss_anchors: int = Field(ge=16, description="anchor points per scene for the pair loss")

    @model_validator(mode="after")
    def _check(self) -> TrainParams:
        if not self.eps1 < self.eps2:
            raise ValueError("train.eps1 must be smaller than train.eps2")
        return self


class EvaluateParams(_Strict):
    iou_threshold: float = Field(gt=0, le=1)
    # A model whose test precision and recall reach these gets the registry alias `accept_alias`.
    accept_precision: float = Field(ge=0, le=1)
    accept_recall: float = Field(ge=0, le=1)
    accept_alias: str


class ImportCaptureParams(_Strict):
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    # Region of interest: a box from roi_min_m to roi_max_m, in the camera frame, or in the frame
    # given by T_cam_from_roi (4 x 4, row-major rows; e.g. the bin frame); null = no crop.
    roi_min_m: tuple[float, float, float] | None
    roi_max_m: tuple[float, float, float] | None
    T_cam_from_roi: tuple[tuple[float, float, float, float], ...] | None
    # The box's -x, +x, -y, +y walls' heights in its frame where lower than roi_max_m z (binpick
    # fit-bin measures them: parts heaped over a low box's rim; 0 = no wall); null = walls to the top.
    roi_wall_heights_m: tuple[float, float, float, float] | None = None

    @field_validator("T_cam_from_roi")
    @classmethod
    def _rigid(cls, T):
        if T is not None:
            M = np.asarray(T, dtype=float)
            if (
                M.shape != (4, 4)
                or not np.allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-6)
                or not np.allclose(M[3], [0, 0, 0, 1])
            ):
                raise ValueError("T_cam_from_roi must be a 4 x 4 rigid transform")
        return T

    plane_threshold_m: float = Field(gt=0)
    plane_ransac_iterations: int = Field(ge=10)
    plane_ransac_confidence: float = Field(gt=0, lt=1, description="RANSAC stops once this sure")
    remove_walls: bool
    max_walls: int = Field(ge=0)
    wall_min_fraction: float = Field(ge=0, le=1, description="smallest wall, share of points")
    keep_above_plane_m: float = Field(ge=0, description="points lower than this are floor")
    # With walls found, keep only points on the bin's side of each: the desk, the room behind.
    crop_to_walls: bool
    voxel_size_m: float = Field(ge=0, description="0 = no downsampling")
    normal_radius_m: float = Field(gt=0)
    outlier_neighbours: int = Field(ge=0, description="statistical outlier removal; 0 = off")
    outlier_std_ratio: float = Field(gt=0)
    # A scene whose extent exceeds this is reported as a unit error (1000x too large).
    max_scene_extent_m: float = Field(gt=0)


class SegmentParams(_Strict):
    n_points: int = Field(ge=64, description="points per network pass; larger scenes are covered by blocks")
    # Centre candidates score above this. null = the value calibrated on the validation scenes
    # when the part was trained (stored in its checkpoint).
    centre_threshold: float | None = Field(gt=0, lt=1)
    # Radius of the non-maximum suppression of centres; null = 0.25 * part diameter.
    nms_radius_m: float | None = Field(gt=0)
    # A point farther than this from every centre in embedding space is noise (-1); null = calibrated.
    embedding_threshold: float | None = Field(gt=0)
    # Ground-truth instances with fewer visible points are not scored, and no smaller instance is kept.
    min_points: int = Field(ge=1)
    # Predicted instances with fewer points become noise (slivers of a part); null = calibrated
    # (at least min_points).
    min_instance_points: int | None = Field(ge=1)
    # A point is a part's where the foreground head's logit is above this; null = calibrated on
    # the validation scenes (0 for checkpoints calibrated before it was).
    foreground_logit: float | None = None


class RegisterParams(_Strict):
    sample_step_rel: float = Field(gt=0, description="model/scene subsampling, share of diameter")
    # A part whose voting grid at sample_step_rel holds fewer model points than this gets a
    # finer grid (and distance bins in proportion): a long thin part's few points cannot tell
    # it from two of it side by side (registration/model.py voting_step).
    min_voting_points: int = Field(ge=1)
    distance_step_rel: float = Field(gt=0, description="PPF distance bin, share of diameter")
    angle_bins: int = Field(ge=4)
    scene_ref_fraction: float = Field(gt=0, le=1)
    cluster_rotation_deg: float = Field(gt=0)
    cluster_translation_rel: float = Field(gt=0)
    icp_iterations: int = Field(ge=0)
    # A last ICP of each verified pose pairing every measured point with the model point on its
    # camera ray (registration/verification.py refine_along_rays): nearest-point ICP pulls a curved
    # part toward the camera under depth noise (sigma^2 / 2r: 1.4-1.8 mm on gear shafts 2 m from a
    # Kinect-class sensor), which puts a suction cup's contact in front of the true surface.
    refine_along_rays: bool = True
    refine_step_rel: float = Field(gt=0, description="grid of the points ICP and scoring use, share of diameter")
    score_inlier_rel: float = Field(gt=0, description="scene point within this of the model counts")
    min_score: float = Field(ge=0, le=1)
    # segments: one pose per segment (then duplicates suppressed); whole_scene: the whole cleaned
    # scene matched without the segments; segments_then_scene: per segment, then the whole scene
    # for parts the segmentation missed or merged. max_instances bounds whole-scene poses.
    mode: Literal["segments", "whole_scene", "segments_then_scene"]
    # The whole-scene pass votes from the points the network calls a part's (`parts`: a carton
    # or a desk beside the bin then gets no pose), or from every cleaned point (`all`: a part the
    # network calls background can still be found, and so can a part-like carton, which the
    # checks below must then refuse).
    scene_votes_from: Literal["parts", "all"] = "all"
    max_instances: int = Field(ge=1)
    # Poses with more than this share of their camera-facing surface in space the camera saw
    # through (in front of what it measured) are dropped; 1 = no such check; null = the value
    # chosen on the validation scenes at training (in the checkpoint).
    max_seen_through: float | None = Field(ge=0, le=1)
    # Poses with less than this share of the surface the camera should have seen supported by a
    # measured point (verification.visible_support) are dropped; 0 = no such check; null = the
    # value chosen on the validation scenes at training (in the checkpoint).
    min_visible_support: float | None = Field(ge=0, le=1)
    # Poses are dropped when less than this share of the points on them is a part's by the
    # network's foreground head (verification.part_share; 0 = no such check; no network: none).
    # Right poses on rendered validation scenes have from 0.78 (IC-BIN cup) and 0.98 (T-joint);
    # on the real cup heap from 0.43 (a cup the network half calls background); the cup posed on
    # a carton face of the real carton frame 0.17. Only where the network is sure it is not the
    # part: its foreground head is trained on renders and calls much of a real frame a part's.
    min_part_share: float = Field(0.3, ge=0, le=1)
    # ... unless at least this share of the surface the camera should have seen is measured on
    # the pose (visible support; null = never): on a sensor it never saw, the foreground head
    # called whole parts background whose right poses had 0.95-0.99 (bench sensors, PhoXi-class
    # bins), while the cup posed on the real frame's cartons had 0.72-0.82.
    part_share_waived_at_support: float | None = Field(0.95, ge=0, le=1)


class SuctionParams(_Strict):
    """A suction gripper: the cup (a cylinder of cup_radius_m, cup_length_m long, its lip at the
    tool centre point; or an oval cup, its lip cup_half_length_m along the tool's x and
    cup_radius_m across) on a tool (a cylinder behind it). A grasp point needs a patch of the part
    that the cup's lip covers, flat within max_deviation_m, its normals within max_normal_deg of
    the cup's axis (a bellows cup seals on that much curvature)."""

    cup_radius_m: float = Field(gt=0, description="the lip's radius (an oval cup's: half its width)")
    cup_half_length_m: float | None = Field(
        None,
        gt=0,
        description="an oval cup: half its lip's length, along the tool's x (null: a round cup); it lies along "
        "the part's least curved direction (a shaft's axis) and turns about its axis only by half a turn",
    )
    cup_length_m: float = Field(gt=0)
    tool_radius_m: float = Field(gt=0)
    tool_length_m: float = Field(gt=0)
    max_deviation_m: float = Field(gt=0)
    max_normal_deg: float = Field(gt=0, lt=90)
    holding_force_n: float = Field(
        gt=0, description="the most the sealed cup holds against the part's weight and the lift's acceleration"
    )
    stroke_m: float = Field(
        0.0,
        ge=0,
        description="a bellows cup's travel along its axis (its data sheet; 0: a flat cup): the tool centre point "
        "is then the lip half pressed, so that the lip seals on a surface up to half the travel nearer or farther "
        "than the pick planned",
    )

    @model_validator(mode="after")
    def _oval(self) -> SuctionParams:
        if self.cup_half_length_m is not None and self.cup_half_length_m < self.cup_radius_m:
            raise ValueError("cup_half_length_m (along the oval lip) must be at least cup_radius_m (across it)")
        return self

    @property
    def oval(self) -> bool:
        return self.cup_half_length_m is not None

    @property
    def lip_half_axes_m(self) -> tuple[float, float]:
        """The lip's half axes along the tool's x and y, metres (equal for a round cup)."""
        return (self.cup_half_length_m or self.cup_radius_m, self.cup_radius_m)


class JawParams(_Strict):
    """A parallel-jaw gripper: two box fingers closing along the tool's x axis, each touching the
    part with a pad at its tip (pad_length_m long, the whole finger by default), the tool centre
    point midway between the pads' centres; a palm behind the fingers and a tool cylinder behind
    the palm. Fingers open to the grasp width plus open_margin_m (at most opening_max_m) to
    approach; contacts need normals within friction_deg of the closing axis."""

    finger_length_m: float = Field(gt=0, description="along the approach")
    pad_length_m: float | None = Field(
        None,
        gt=0,
        description="the contact pad at the finger's tip, along the approach (null: the whole finger); a short pad"
        " on a long finger reaches across a part thicker than the finger (a shaft) without the palm touching it",
    )
    finger_width_m: float = Field(gt=0, description="across the approach and the closing axis")
    finger_thickness_m: float = Field(gt=0, description="along the closing axis")
    opening_min_m: float = Field(ge=0)
    opening_max_m: float = Field(gt=0)
    open_margin_m: float = Field(ge=0)
    palm_depth_m: float = Field(gt=0)
    palm_width_m: float = Field(gt=0)
    tool_radius_m: float = Field(gt=0)
    tool_length_m: float = Field(gt=0)
    friction_deg: float = Field(gt=0, lt=90)
    grip_force_n: float = Field(
        gt=0, description="each jaw's closing force (the hold is friction: tan(friction_deg) x 2 x this)"
    )

    @model_validator(mode="after")
    def _opening(self) -> JawParams:
        if self.opening_min_m >= self.opening_max_m:
            raise ValueError("jaw.opening_min_m must be below jaw.opening_max_m")
        if self.pad_length_m is not None and self.pad_length_m > self.finger_length_m:
            raise ValueError("jaw.pad_length_m must not exceed jaw.finger_length_m")
        return self

    @property
    def pad_m(self) -> float:
        """The pad's length along the approach."""
        return self.finger_length_m if self.pad_length_m is None else self.pad_length_m

    @property
    def palm_from_tcp_m(self) -> float:
        """How far behind the tool centre point the fingers meet the palm."""
        return self.finger_length_m - self.pad_m / 2.0


PICK_ORDER_KEYS = ("height", "score", "clearance")


class PickParams(_Strict):
    """Picks (binpick/picking/plan.py): the gripper, where it may come from and how parts are ranked."""

    gripper: Literal["suction", "jaw"]
    suction: SuctionParams
    jaw: JawParams
    max_grasps: int = Field(ge=1, description="generated grasps per part, before the symmetry expands them")
    approach_cone_deg: float = Field(
        ge=0, le=90, description="approach at most this far from straight down the bin's up axis"
    )
    fallback_cone_deg: float | None = Field(
        ge=0,
        le=90,
        description="a part with no collision-free grasp within approach_cone_deg may be taken from up to this far "
        "(null: never)",
    )
    pregrasp_distance_m: float = Field(ge=0, description="the pre-grasp pose: this far back along the approach")
    retreat_distance_m: float = Field(
        ge=0, description="the post-grasp pose: this far back along the approach (or up the bin: picking/lift.py)"
    )
    leave_straight_up: bool = Field(
        True,
        description="a grasp tilted from the bin's down axis whose part, pulled back along the approach, drags into "
        "a neighbour may leave straight up the bin instead, the tool's way up checked (picking/lift.py)",
    )
    lift_past_parts: bool = Field(
        True,
        description="when no detected part comes out of the heap free, take the one whose way out only its "
        "neighbours block (not the bin), those pushing the fewest parts first (picking/plan.py); false: report no pick",
    )
    clearance_m: float = Field(ge=0, description="the swept gripper keeps at least this from every obstacle")
    room_m: float = Field(
        0.006,
        ge=0,
        description="a part's grasps whose swept gripper keeps less than this from everything (but clearance_m) "
        "are tried after its others: a neighbour leaning on the part falls into the room it leaves, toward the tool",
    )
    own_points_m: float = Field(gt=0, description="captured points this near the target's posed model are its own")
    max_seen_through: float = Field(
        ge=0,
        le=1,
        description="a pose with more of its camera-facing surface where the camera saw through it is picked last "
        "(tighter than register's)",
    )
    order: list[Literal["height", "score", "clearance"]] = Field(min_length=1)
    height_tolerance_m: float = Field(ge=0, description="parts this close in height count as equally high")
    max_candidates_per_part: int = Field(ge=1, description="grasps tried per part, best-ranked first")
    part_priority: list[str] = Field(
        [],
        description="a mixed bin (several parts in one request): these parts are picked first, in this order; "
        "the rest, and every part when empty, by `order` whatever the part (a request's own priority wins)",
    )
    part_quota: dict[str, int] = Field(
        {},
        description="a mixed bin: at most this many picks of a part in one answer (a kit's count of it; 0: none of "
        "it, its poses stay obstacles); parts not named: no limit (a request's own quota wins)",
    )
    pose_format: Literal["matrix", "ur", "abb", "kuka", "fanuc"] = Field(  # binpick.robot.pose_formats
        "matrix",
        description="picks.json and the service also give each pick's base-frame tool poses in this robot's "
        "convention: matrix (only the 4 x 4 matrices in metres), ur, abb, kuka or fanuc (docs: robot poses)",
    )
    T_base_from_cam: list[list[float]] | None = Field(
        description="eye-to-hand calibration (binpick hand-eye); null = not calibrated"
    )

    @field_validator("order")
    @classmethod
    def _unique_order(cls, order: list[str]) -> list[str]:
        if len(set(order)) != len(order):
            raise ValueError(f"pick.order repeats a key: {order}")
        return order

    @model_validator(mode="after")
    def _fallback_wider(self) -> PickParams:
        if self.fallback_cone_deg is not None and self.fallback_cone_deg < self.approach_cone_deg:
            raise ValueError(
                f"pick.fallback_cone_deg ({self.fallback_cone_deg:g}) is narrower than pick.approach_cone_deg "
                f"({self.approach_cone_deg:g})"
            )
        return self

    @field_validator("T_base_from_cam")
    @classmethod
    def _rigid(cls, T: list[list[float]] | None) -> list[list[float]] | None:
        return None if T is None else rigid_matrix(T, "pick.T_base_from_cam")

    @property
    def gripper_length_m(self) -> float:
        """How far behind the tool centre point the modelled gripper ends, where it meets the
        flange: the suction cup and its tool, or the jaws' fingers (back from the pad's middle),
        palm and tool (binpick/picking/gripper.py)."""
        if self.gripper == "suction":
            return self.suction.cup_length_m + self.suction.tool_length_m
        return self.jaw.palm_from_tcp_m + self.jaw.palm_depth_m + self.jaw.tool_length_m

    @property
    def oval_cup(self) -> bool:
        """Whether the gripper in use is an oval suction cup (its grasps name their long axis)."""
        return self.gripper == "suction" and self.suction.oval


def rigid_matrix(T: list[list[float]], name: str) -> list[list[float]]:
    """T, checked to be a 4 x 4 rigid transform (ValueError naming `name` otherwise)."""
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ValueError(f"{name} must be a 4 x 4 matrix of numbers")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0 or not np.allclose(M[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a rigid transform (a rotation and a translation, last row 0 0 0 1)")
    return T


class PlaceParams(_Strict):
    """Where a picked part is put, in the robot's base frame (binpick/picking/arm.py)."""

    kind: Literal["fixture", "conveyor", "drop"] = Field(
        description="fixture: the part at exactly T_base_from_part; conveyor: any turn of it about the base's "
        "vertical; drop: its centre at that position, any orientation"
    )
    T_base_from_part: list[list[float]] = Field(description="the part's pose at the place (model frame)")
    above_m: float = Field(ge=0, description="the part comes down onto the place from this far above it")
    tolerance_m: float = Field(gt=0, description="a part within this of the place arrived (bench cell)")
    tolerance_deg: float = Field(gt=0, description="... and within this of its orientation (fixture)")

    @field_validator("T_base_from_part")
    @classmethod
    def _rigid(cls, T: list[list[float]]) -> list[list[float]]:
        return rigid_matrix(T, "cell.place.T_base_from_part")


class RobotParams(_Strict):
    """The robot `binpick cell run` drives (binpick/cell/robot.py)."""

    driver: Literal["sim", "ur_rtde"] = Field(description="sim: the physics cell; ur_rtde: a Universal Robots arm")
    host: str = Field(description="ur_rtde: the controller's address")
    vacuum_out: int = Field(ge=0, le=7, description="ur_rtde: the standard digital output that switches the vacuum")
    vacuum_in: int | None = Field(
        ge=0, le=7, description="ur_rtde: the standard digital input of the vacuum sensor (null: none, hold assumed)"
    )
    grip_s: float = Field(ge=0, description="the arm waits this long at the grasp for the vacuum (the jaws)")
    release_s: float = Field(ge=0, description="... and this long at the place for the release")


class CellParams(_Strict):
    """The robot arm around the pipeline (binpick/robot, binpick/picking/arm.py): which arm, the tool
    on its flange, its home, the place; picks are checked for the whole arm when `arm` is set and
    pick.T_base_from_cam says where the camera is."""

    arm: Literal["ur5e", "ur3e", "ur10"] | None = Field(
        description="the arm (URDF from airo-models or example-robot-data, ur_analytic_ik IK); null: picks "
        "checked for the gripper only"
    )
    T_flange_from_tcp: list[list[float]] | None = Field(
        description="the tool on the flange: its centre point (the cup's lip, the jaws' middle) in the flange frame; "
        "null: straight out along the flange's z by the pick gripper's modelled length"
    )
    home_q_rad: list[float] = Field(min_length=6, max_length=6, description="joint angles the cell starts from")
    place: PlaceParams
    turn_step_deg: float = Field(
        gt=0, le=180, description="a suction cup's free turn about its axis is tried in steps of this"
    )
    joint_limit_margin_deg: float = Field(ge=0, description="configurations keep this far from every joint limit")
    min_singularity: float = Field(
        ge=0, lt=1, description="configurations keep at least this sine from the arm's singularities"
    )
    arm_clearance_m: float = Field(ge=0, description="the arm's links keep this far from everything measured")
    table_z_m: float = Field(
        description="the table the arm stands on, in the base frame (0: its mounting face): no link comes below it"
    )
    lift_m: float = Field(gt=0, description="the part is lifted this far above its grasp before the arm turns away")
    max_step_rad: float = Field(gt=0, le=0.5, description="paths are checked at joint steps of at most this")
    speed_scaling: float = Field(gt=0, le=1, description="share of the arm's rated joint speed and acceleration")
    robot: RobotParams

    @field_validator("T_flange_from_tcp")
    @classmethod
    def _rigid(cls, T: list[list[float]] | None) -> list[list[float]] | None:
        return None if T is None else rigid_matrix(T, "cell.T_flange_from_tcp")


class RenderDemoParams(_Strict):
    """The built-in demo capture: a synthetic bin rendered at full camera resolution."""

    part: str
    n_objects: int = Field(ge=1)
    downscale: int = Field(ge=1, description="replaces camera.downscale for the demo capture")

    @field_validator("part")
    @classmethod
    def _safe_part(cls, part: str) -> str:
        return check_name(part, "part")


class ZividCameraParams(_Strict):
    """Zivid capture settings (one acquisition)."""

    serial: str = Field(description="camera serial number; '' = the first camera found")
    exposure_time_us: float = Field(gt=0)
    aperture: float = Field(gt=0, description="f-number")
    brightness: float = Field(ge=0)
    gain: float = Field(gt=0)


class LearnParams(_Strict):
    """Learning from the cell (binpick.learning): captures whose poses passed verification with
    margin label themselves; a part's network is fine-tuned on them plus its synthetic scenes
    once enough reviewed ones are new, and served only when it is no worse on both."""

    # A pose is trusted when its verification score clears register.min_score by this much.
    trust_margin: float = Field(ge=0, le=1)
    min_new_scenes: int = Field(
        ge=1, description="reviewed captures not yet learnt from before the scheduled retraining fine-tunes"
    )
    heldout_share: float = Field(
        gt=0, lt=1, description="share of the reviewed captures kept out of fine-tuning to judge it"
    )
    finetune_epochs: int = Field(ge=1)
    finetune_learning_rate: float = Field(gt=0)
    # The fine-tuned network may lose at most this much precision or recall on either test set.
    max_drop: float = Field(ge=0, le=1)
    serve_alias: str = Field(min_length=1, description="MLflow registry alias of the network the service serves")


class ServiceParams(_Strict):
    """`binpick service`: the resident pick service (flows/service.py)."""

    host: str = Field(description="address to bind; beyond loopback only with a token")
    http_port: int = Field(ge=1, le=65535)
    tcp_port: int = Field(ge=0, le=65535, description="the JSON line protocol; 0 = off")
    token_env: str = Field(description="environment variable holding the access token; unset or empty = no token")
    max_request_mb: float = Field(gt=0)
    max_requests_per_min: int = Field(ge=1)
    max_queue: int = Field(ge=1, description="requests waiting beyond the one being answered; more are refused as busy")
    keep_requests: int = Field(ge=0, description="the newest requests kept for review; older ones are deleted")
    keep_dir: str = Field(description="where kept requests go, inside the project")
    capture_folders: list[str] = Field(description="folders (besides the project) a request may name a capture file in")

    @field_validator("keep_dir")
    @classmethod
    def _safe_keep_dir(cls, path: str) -> str:
        return check_project_path(path, "service.keep_dir")


class TrackingParams(_Strict):
    # null: a sqlite store in the project (mlflow.db). Any MLflow URI otherwise.
    mlflow_uri: str | None


class OrchestrationParams(_Strict):
    """How Prefect runs the pipeline. Not tracked by DVC: none of it changes a result."""

    # `binpick serve`: when the watcher runs (cron, in schedule_timezone). Default: nightly 02:00.
    schedule_cron: str
    schedule_timezone: str
    # Fan-out of scene generation and evaluation: `processes` (a local process pool) or `dask`
    # (a Dask cluster: the one at dask_address, or a local one of `workers` processes).
    task_runner: Literal["processes", "dask"]
    dask_address: str | None
    workers: int = Field(ge=0, description="processes or local Dask workers; 0 = one per CPU core")

    @field_validator("schedule_cron")
    @classmethod
    def _five_fields(cls, cron: str) -> str:
        if len(cron.split()) != 5:
            raise ValueError(f"{cron!r} is not a cron expression of 5 fields (minute hour day month weekday)")
        return cron


class Params(_Strict):
    seed: int = Field(ge=0, lt=2**63, description="root of every random generator (derive_seed)")
    profile: str
    parts: dict[str, PartParams]
    captures: dict[str, CaptureParams] = {}
    ingest: IngestParams
    camera: CameraParams
    generate: GenerateParams
    train: TrainParams
    evaluate: EvaluateParams
    import_capture: ImportCaptureParams
    segment: SegmentParams
    registration: RegisterParams = Field(alias="register")
    render_demo: RenderDemoParams
    pick: PickParams
    cell: CellParams
    service: ServiceParams
    learn: LearnParams
    zivid_camera: ZividCameraParams
    tracking: TrackingParams
    orchestration: OrchestrationParams

    @field_validator("parts")
    @classmethod
    def _part_names(cls, parts: dict[str, PartParams]) -> dict[str, PartParams]:
        for name in parts:
            check_name(name, "part")
        return parts

    @field_validator("captures")
    @classmethod
    def _capture_names(cls, captures: dict[str, CaptureParams]) -> dict[str, CaptureParams]:
        for name in captures:
            check_name(name, "capture")
        return captures

    @field_validator("profile")
    @classmethod
    def _profile_name(cls, profile: str) -> str:
        return check_name(profile, "profile")

    def import_capture_for(self, capture: str | None) -> ImportCaptureParams:
        """The import_capture section with a listed capture's own overrides applied."""
        if not capture or not self.captures[capture].import_capture:
            return self.import_capture
        try:
            return ImportCaptureParams.model_validate(
                deep_merge(self.import_capture.model_dump(), self.captures[capture].import_capture)
            )
        except ValidationError as exc:
            raise ParamsError(f"captures.{capture}.import_capture: {_one_line(exc)}") from None

    @model_validator(mode="after")
    def _captures_name_parts(self) -> Params:
        for name, capture in self.captures.items():
            for part in capture.part_names:
                if part not in self.parts:
                    raise ValueError(f"capture {name!r} names part {part!r}, which is not in parts")
        if self.render_demo.part not in self.parts:
            raise ValueError(f"render_demo.part {self.render_demo.part!r} is not in parts")
        for key, named in (
            ("pick.part_priority", self.pick.part_priority),
            ("pick.part_quota", list(self.pick.part_quota)),
            ("generate.clutter.parts", self.generate.clutter.parts),
        ):
            unknown = [n for n in named if n not in self.parts]
            if unknown:
                raise ValueError(f"{key} names {', '.join(unknown)}, not in parts")
        if any(n < 0 for n in self.pick.part_quota.values()):
            raise ValueError(f"pick.part_quota counts picks: 0 or more, got {self.pick.part_quota}")
        return self

    @model_validator(mode="after")
    def _tool_on_the_flange(self) -> Params:
        """The cell's T_flange_from_tcp: when null, the pick gripper straight out along the
        flange's z; when set (for an arm), it must put the flange where the modelled gripper ends,
        or the arm check would leave a gap between them unchecked, or a tool inside the wrist."""
        length = self.pick.gripper_length_m
        if self.cell.T_flange_from_tcp is None:
            T = np.eye(4)
            T[2, 3] = length
            return self.model_copy(update={"cell": self.cell.model_copy(update={"T_flange_from_tcp": T.tolist()})})
        if self.cell.arm is not None:
            T = np.asarray(self.cell.T_flange_from_tcp, dtype=float)
            flange_in_tcp = -T[:3, :3].T @ T[:3, 3]
            if np.linalg.norm(flange_in_tcp - [0.0, 0.0, -length]) > TOOL_MOUNT_TOLERANCE_M:
                x, y, z = flange_in_tcp
                raise ValueError(
                    f"cell.T_flange_from_tcp puts the flange at ({x:.3f}, {y:.3f}, {z:.3f}) m in the tool frame, but "
                    f"pick's {self.pick.gripper} gripper ends {length:.3f} m straight behind its tool centre point "
                    f"({GRIPPER_LENGTH_KEYS[self.pick.gripper]}): make them agree, or set it to null to mount the "
                    "gripper as modelled"
                )
        return self


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Return `base` with `override` applied; nested mappings merge, other values replace."""
    merged = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def resolve(raw: dict[str, Any], part: str | None = None) -> dict[str, Any]:
    """Apply the active profile and, when `part` is given, that part's overrides to the sections."""
    profile = raw.get("profile")
    profiles = raw.get("profiles") or {}
    if profile not in profiles:
        raise ParamsError(f"profile {profile!r} is not defined under 'profiles' (have: {sorted(profiles)})")
    missing = [s for s in SECTIONS if s not in (profiles[profile] or {})]
    if missing:
        # DVC tracks profiles.<profile>.<section>, so a missing key would make `dvc repro` fail.
        raise ParamsError(f"profiles.{profile} must list every section (use {{}}); missing: {missing}")
    resolved = {k: v for k, v in raw.items() if k != "profiles"}
    for section in SECTIONS:
        resolved[section] = deep_merge(raw.get(section) or {}, profiles[profile][section] or {})
    if part is not None:
        parts = raw.get("parts") or {}
        if part not in parts:
            raise ParamsError(f"part {part!r} is not listed under 'parts' (have: {sorted(parts)})")
        for section in PER_PART_SECTIONS:
            resolved[section] = deep_merge(resolved.get(section) or {}, (parts[part] or {}).get(section) or {})
        surface = (parts[part] or {}).get("surface")
        if (
            surface is not None
            and isinstance(resolved.get("generate"), dict)
            and isinstance(resolved["generate"].get("sensor"), dict)
        ):
            resolved["generate"]["sensor"]["surface"] = surface
    return resolved


def _one_line(err: ValidationError) -> str:
    first = err.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    message = str(first["msg"]).removeprefix("Value error, ")
    return f"{where}: {message}{more}" if where else f"{message}{more}"


class _UniqueKeys(yaml.SafeLoader):
    """YAML's safe loader refusing a key twice in one mapping: PyYAML keeps the last silently, and
    a part entry with `pick:` written twice took the second without a word."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                line = key_node.start_mark.line + 1
                raise yaml.constructor.ConstructorError(None, None, f"the key {key!r} twice (line {line})")
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_raw(path: str | Path) -> dict[str, Any]:
    """Read params.yaml as plain data."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "params file not found")
    try:
        raw = yaml.load(path.read_text(), Loader=_UniqueKeys)  # a safe loader that refuses repeated keys
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise InputError(path, "expected a mapping of sections")
    return raw


def _validate(data: dict[str, Any], where: str) -> Params:
    try:
        return Params.model_validate(data)
    except ValidationError as exc:
        raise ParamsError(f"{where}{_one_line(exc)}") from None


def check_whole(raw: dict[str, Any]) -> None:
    """Validate the whole settings file, not only what one stage reads: every top-level key,
    the base sections on their own (a bad value that the active profile happens to override is
    still a bad value), every profile, every part's overrides (errors name the part's entry) and
    every capture's import overrides. Raises ParamsError with one line."""
    known = {f.alias or name for name, f in Params.model_fields.items()} | {"profiles"}
    for key in raw:
        if key not in known:
            close = difflib.get_close_matches(str(key), sorted(known), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (sections: {', '.join(sorted(known))})"
            raise ParamsError(f"unknown top-level key {key!r}{hint}")
    profiles = raw.get("profiles")
    if not isinstance(profiles, dict) or not profiles:
        raise ParamsError("'profiles' must map profile names to their section overrides")
    for name, overrides in profiles.items():
        try:
            check_name(name, "profile")
        except ValueError as exc:
            raise ParamsError(f"profiles: {exc}") from None
        if not isinstance(overrides, dict):
            raise ParamsError(f"profiles.{name}: expected a mapping of sections")
        for section, value in overrides.items():
            if section not in SECTIONS:
                close = difflib.get_close_matches(str(section), SECTIONS, n=1)
                raise ParamsError(
                    f"profiles.{name}: {section!r} is not a section a profile overrides"
                    + (f" (did you mean {close[0]!r}?)" if close else "")
                )
            if value is not None and not isinstance(value, dict):
                raise ParamsError(f"profiles.{name}.{section}: expected a mapping ({{}} for no change)")
    _validate({k: v for k, v in raw.items() if k != "profiles"}, "")
    for name in profiles:
        _validate(resolve({**raw, "profile": name}), f"profiles.{name}: ")
    active = _validate(resolve(raw), "")
    for part in active.parts:
        _validate(resolve(raw, part), f"parts.{part}: ")
    for capture in active.captures:
        active.import_capture_for(capture)


def load_params(path: str | Path = "params.yaml", part: str | None = None) -> Params:
    """Load, validate the whole file (check_whole), and resolve for `part`; a bad key or value
    anywhere in the file fails here with one line."""
    raw = load_raw(path)
    try:
        check_whole(raw)
        return _validate(resolve(raw, part), "")
    except ParamsError as exc:
        raise ParamsError(f"{path}: {exc}") from None


def part_name_for(mesh_path: str | Path) -> str:
    """A valid part name from a mesh file name: lower case, other characters as '_'."""
    stem = Path(mesh_path).stem.lower()
    name = "".join(c if c.isalnum() or c in "_-" else "_" for c in stem).strip("_-")
    return name or "part"


def add_parts(path: str | Path, meshes: dict[str, str], unit: str = "auto") -> None:
    """Add parts (name -> mesh path) to params.yaml under `parts`, keeping comments and order.

    New parts get `unit` (default: a logged guess at ingest) and no symmetry; edit their entries
    to declare them. The result is validated before it replaces the file.
    """
    _add_entries(
        path,
        "parts",
        {name: {"mesh": mesh, "unit": unit, "symmetry": {"kind": "none"}} for name, mesh in meshes.items()},
    )


def add_captures(path: str | Path, files: dict[str, str], part: str | list[str], unit: str = "mm") -> None:
    """Add captures (name -> file path) of `part` (or of the parts of a mixed bin, a list) to
    params.yaml under `captures`, keeping comments; validated before it replaces the file.
    Optional keys (truth, intrinsics) are left out, as a user would write the entry."""
    key: dict[str, str | list[str]] = {"parts": list(part)} if isinstance(part, list) else {"part": part}
    _add_entries(path, "captures", {name: {"file": file, **key, "unit": unit} for name, file in files.items()})


def set_capture_overrides(path: str | Path, capture: str, overrides: dict[str, Any]) -> None:
    """Set keys of `captures.<capture>.import_capture` in params.yaml, keeping comments;
    validated as a whole before it replaces the file."""

    def change(doc: Any) -> None:
        entry = (doc.get("captures") or {}).get(capture)
        if entry is None:
            raise ParamsError(f"{path}: capture {capture!r} is not listed under 'captures'")
        if entry.get("import_capture") is None:
            entry["import_capture"] = {}
        for key, value in overrides.items():
            entry["import_capture"][key] = value

    _edit(path, change)


def set_section_key(path: str | Path, section: str, key: str, value: Any) -> None:
    """Set `<section>.<key>` in params.yaml (e.g. pick.T_base_from_cam from hand-eye), keeping
    comments; validated as a whole before it replaces the file."""

    def change(doc: Any) -> None:
        if doc.get(section) is None:
            raise ParamsError(f"{path}: has no {section!r} section")
        doc[section][key] = value

    _edit(path, change)


def _add_entries(path: str | Path, section: str, entries: dict[str, dict[str, Any]]) -> None:
    def change(doc: Any) -> None:
        if doc.get(section) is None:
            doc[section] = {}
        for name, entry in entries.items():
            if name in doc[section]:
                raise ParamsError(f"{path}: {section} already has {name!r}")
            doc[section][name] = entry

    _edit(path, change)


def _edit(path: str | Path, change: Callable[[Any], None]) -> None:
    """Apply `change` to params.yaml's document, keeping comments and order; the result is
    validated as a whole (check_whole) before it replaces the file."""
    import io

    from ruamel.yaml import YAML

    from binpick.io.atomic import write_text

    path = Path(path)
    yaml_rt = YAML()
    yaml_rt.preserve_quotes = True
    doc = yaml_rt.load(path.read_text())
    change(doc)
    buffer = io.StringIO()
    yaml_rt.dump(doc, buffer)
    text = buffer.getvalue()
    try:
        check_whole(yaml.safe_load(text))
    except ParamsError as exc:
        raise ParamsError(f"{path}: {exc}") from None
    write_text(path, text)
