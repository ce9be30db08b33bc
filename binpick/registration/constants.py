"""The PPF matcher's settings that are not params: each changes results, so each is named and
explained here, in one place; and the lengths of the matcher, all derived from one scale (the
part's diameter) and the shares in the `register` params."""

from __future__ import annotations

import math
from dataclasses import dataclass

from binpick.io.ppf_model import PPFModel
from binpick.params import RegisterParams

# Per segment: the strongest accumulator peaks that are clustered (weak peaks, from references on
# clutter or ambiguous patches, decide nothing) ...
MAX_CLUSTER_CANDIDATES = 160
# ... the clusters refined by coarse ICP and scored (comparing clusters only after ICP keeps a
# pose slid along a long part from winning) ...
TOP_CLUSTERS = 4
# ... and, of those, the best refined again by fine ICP and scored on every model point.
FINE_CLUSTERS = 2
# Model points used: coarse ICP every 4th dense point, fine ICP every 2nd, scoring every 2nd.
COARSE_STRIDE = 4
FINE_STRIDE = 2
SCORE_STRIDE = 2
# A whole-scene score counts a pose's facing surface where the sensor measured nothing as neutral,
# but divides by at least this share of that surface (verification.whole_scene_share).
MIN_MEASURED_SHARE = 0.5
# The inlier distance is at least this many times the capture's depth noise (register.with_capture_noise).
NOISE_INLIER_SIGMAS = 1.0
# A segment votes from at least this many reference points (all of its points on the voting grid
# if fewer), whatever scene_ref_fraction says: a small segment's fifth drew too few references to
# be sure of its pose (an upright IC-BIN cup seen lid-on, 277 grid points: its right pose won on 7
# of 8 draws of 55 references, on 8 of 8 from 100 up, in about the same time).
MIN_SEGMENT_REFS = 100
# Accumulator peaks kept per scene reference point.
PEAKS_PER_REFERENCE = 2
# Whole-scene voting: references per accumulator (it holds references x model points x angles).
SCENE_REFS_PER_CHUNK = 64
# Whole-scene matching: clusters refined per instance sought.
SCENE_CLUSTERS_PER_INSTANCE = 3
# Non-maximum suppression by support: a pose is dropped when more than this share of its
# supporting scene points is explained by a better pose already.
MAX_SHARED_SUPPORT = 0.3
# Whole-scene matching after poses are known votes only from the points they leave unexplained,
# and not at all when those are fewer than this share of the model's points on the voting grid
# (less than a tenth of a part's surface: edges and noise, no part the pass could fit). A fifth
# stopped the pass before a T-joint standing on end in a bin's corner (0.11 of its points left
# in one patch) or one half in a projector's shadow (0.15).
MIN_FREE_SHARE = 0.1
# A segment this share of whose points (voting grid) poses found on larger segments explain is
# a fragment of those parts and is not matched (the rest of it could not hold a part either).
SEGMENT_EXPLAINED_SHARE = 0.8
# ICP stops when fitness and RMSE change by less than this, relative.
ICP_RELATIVE_CHANGE = 1e-4

# Near symmetries (model.py, near_symmetry.py): turns that are not declared symmetries but map
# nearly all of a part's surface onto itself. Turns tried about each principal axis: multiples of
# this angle; a pose found is within half a step of the right turn, which fine ICP then reaches
# (the distinguishing feature pulls it).
NEAR_SYMMETRY_STEP_DEG = 30
# A turn is a near symmetry when it brings this share of the surface to within the score's inlier
# distance of the surface: the coffee cup of the IC-BIN frame turned about its axis keeps 0.94-0.97
# (the relief of its lid is the rest: it has no handle); no turn of the T-joint, gear shaft, ring screw or three-way
# pipe other
# than their declared symmetries keeps more than 0.61.
NEAR_SYMMETRY_MIN_OVERLAP = 0.85
# A turn that brings this share of the surface to within 1.5 inlier distances of it is a symmetry
# the part was not declared with, not a near one: no capture tells its poses apart, so it is not
# tried. A plain cylinder's turns bring 1.000 (sampling puts no point farther than 1.5 inlier
# distances), the IC-BIN cup's 0.961-0.988, a mug with a 5 % handle 0.951.
NEAR_SYMMETRY_EXACT_SHARE = 0.998
# Every k-th dense point is used to measure the overlap.
NEAR_SYMMETRY_PROBE_STRIDE = 4
# A pose and its turns are compared by how near the scene points around them lie to each posed
# surface, up to this share of the score's inlier distance (registration/near_symmetry.py): the
# IC-BIN cup's lid relief is a few millimetres, its inlier distance 2.7 mm. Cup, 8 cluttered scenes
# of `bench clutter`, with a fixed radius (first scene draw / second): 0.5 and 0.3 gave pose
# precision / recall 0.97 / 0.94 and 0.94 / 0.94, 1.0 gave 0.92 / 0.84 and 0.79 / 0.78.
NEAR_SYMMETRY_RESIDUAL_REL = 0.5
# ... and at least this many times the noise of the scene points about the pose.
NEAR_SYMMETRY_NOISE_FACTOR = 2.5


@dataclass(frozen=True)
class Scales:
    """Every length of the matcher, metres: shares (params) of one scale, the part diameter.

    sample_step_m: voxel grid of model and scene for voting; refine_step_m: grid of the scene
    points that ICP and scoring use; inlier_m: a scene point this close to the model surface
    agrees with it; coarse_icp_m / fine_icp_m: ICP correspondence distances; reach_m: radius
    around a pose's model centre within which scene points can belong to it;
    cluster_translation_m: poses closer than this (and cluster_rotation_deg) are one cluster.
    """

    diameter_m: float
    sample_step_m: float
    refine_step_m: float
    inlier_m: float
    coarse_icp_m: float
    fine_icp_m: float
    reach_m: float
    cluster_translation_m: float

    @classmethod
    def of(cls, model: PPFModel, params: RegisterParams) -> Scales:
        """The lengths for a part's PPF model: its diameter and voting grid (the params' grid for
        a model file written before the grid was stored)."""
        diameter_m = model.diameter_m
        # Each product is written as it always was: the same floating-point results.
        inlier = params.score_inlier_rel * diameter_m
        step = model.sample_step_m if math.isfinite(model.sample_step_m) else params.sample_step_rel * diameter_m
        return cls(
            diameter_m=diameter_m,
            sample_step_m=step,
            refine_step_m=params.refine_step_rel * diameter_m,
            inlier_m=inlier,
            coarse_icp_m=2.0 * step,
            fine_icp_m=2.0 * inlier,
            reach_m=0.5 * diameter_m + 2.0 * step,
            cluster_translation_m=params.cluster_translation_rel * diameter_m,
        )


# Verification against what the camera saw (visibility.py): a posed model point counts as seen
# through when it lies this far (share of the part diameter, at least the floor below) in front
# of the measured depth along its ray; below that it is sensor noise or a silhouette pixel.
SEEN_THROUGH_MARGIN_REL = 0.05
SEEN_THROUGH_MARGIN_MIN_M = 0.003
# A part cannot lie inside the support plane the cleaning found (the bin's floor, or the table
# under it): a pose whose surface reaches more than this share of the part's diameter below it
# is refused. Bench sensors' clutter bins (tilts to 45 degrees, the `cpu` networks, 8 bins a
# preset): right poses reach at most 0.15 d below (pose error, the plane fitted to the table 5 mm
# under the bin's floor), wrong ones fitted into the floor 0.26 d and 0.41 d; with the inlier
# distance widened by a Kinect-class capture's noise, two wrong ones at 0.245 d (6 bins).
MAX_BELOW_FLOOR_REL = 0.2
# On a noisy capture less of a right pose's surface has a measured point within the inlier
# distance: the visible support's cut is lowered by up to SUPPORT_NOISE_RELIEF as the capture's
# depth noise about the pose (geometry/depth_noise.py) grows from half the inlier distance to
# one and a half. Bench sensors' bins, T-joint, all poses before the checks: Kinect-class (2 mm
# of noise, 1.4 mm of inlier distance) right poses 0.62-0.69 at 0.5-0.8 mm ADD, 46 of 59 kept at
# 0.7, 55 at 0.6, no wrong one at either; widening the inlier distance instead let 3 of 5 wrong
# ones through. Today's camera, PhoXi and Zivid (0.2-0.6 mm) keep 0.7.
SUPPORT_NOISE_RELIEF = 0.1
# The verification threshold when none was chosen at training (register.max_seen_through null
# and no checkpoint, e.g. whole-scene registration without a network): on cluttered T-joint bins
# true poses have 0.00-0.03, estimates within ADD 0.1 d up to 0.28, wrong ones from 0.43.
DEFAULT_MAX_SEEN_THROUGH = 0.35
# The least visible support (visibility.py) when none was chosen at training (register.min_visible_support
# null and no checkpoint, or a checkpoint calibrated before it existed). Bench clutter scenes of the
# T-joint, gear shaft, ring screw and pipe (13 per part, two scene seeds, tilts to 45 degrees, the
# seen-through check only): a cut at 0.7 keeps 437 of 451 right poses and 9 of 38 wrong ones
# (support over all facing surface, cut at 0.5: 444 and 26); 0.75 does as well there (432 and 7, a
# wrong pose counting twice) but cost bench clutter's recall (8 scenes: T-joint 0.918, gear shaft
# 0.887). A part's verify stage chooses its own cut from this prior (the IC-BIN cup's: 0.90).
DEFAULT_MIN_VISIBLE_SUPPORT = 0.7
# The visible support counts only the posed surface the camera meets at most this far from head-on.
# At grazing incidence no sensor's depth is trustworthy (mixed pixels, incidence dropout and noise)
# and a pose a millimetre off moves silhouette points onto the background: counted, these made
# right poses look unsupported. Right IC-BIN cup poses on the cup network's Kinect-class validation
# renders had 0.49-0.85 over all facing points and 0.90-1.00 below 65 degrees; on the real cup frame
# 0.91-1.00 and 0.94-1.00; the cup poses the real carton frame gave (a cup fitted into a carton face)
# 0.67-0.74 and 0.72-0.82. A cut much lower leaves too little surface on a part seen edge-on.
SUPPORT_MAX_INCIDENCE_DEG = 65.0
