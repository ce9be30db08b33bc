"""The bin as a box, the one type for it: fitted to a capture (cell/bin_fit.py), given in params
(import_capture's region of interest), an obstacle to the gripper (picking/plan.py), and the up
axis picks approach along (support_frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from binpick.geometry.transforms import transform_points
from binpick.params import BinParams, ImportCaptureParams

# A bin box's floor is the support plane unless the plane found in the capture agrees with it
# within these (then the measured plane is used: it is where the parts lie today).
BIN_PLANE_AGREEMENT_DEG = 10.0
BIN_PLANE_AGREEMENT_M = 0.02
# A plane found in a capture is one of a given box's walls when it is parallel to a side within
# BIN_PLANE_AGREEMENT_DEG and lies in this outer share of the box's half size toward that side (a
# fitted box runs to the walls' outer faces and a few centimetres of noise beyond).
WALL_OUTER_SHARE = 0.25
# The order of a box's four walls wherever they are listed (wall_heights_m, roi_wall_heights_m).
WALL_SIDES = ("-x", "+x", "-y", "+y")


@dataclass(frozen=True)
class BinBox:
    """T_cam_from_bin (4, 4), z up from the bin's floor; inner_min_m / inner_max_m (3,) its inner
    corners in that frame, metres. As an obstacle: its floor and four walls, up to inner_max_m z
    or to wall_heights_m (4,): the -x, +x, -y, +y walls' heights in that frame (a box whose parts
    are heaped over its rim; 0 or less: no wall there, e.g. a heap on a table)."""

    T_cam_from_bin: np.ndarray
    inner_min_m: np.ndarray
    inner_max_m: np.ndarray
    wall_heights_m: np.ndarray | None = None

    @classmethod
    def of_import(cls, params: ImportCaptureParams) -> BinBox | None:
        """The bin given in params (import_capture's region of interest with its frame), else None."""
        if params.T_cam_from_roi is None or params.roi_min_m is None or params.roi_max_m is None:
            return None
        return cls(
            np.asarray(params.T_cam_from_roi, dtype=np.float64),
            np.asarray(params.roi_min_m, float),
            np.asarray(params.roi_max_m, float),
            None if params.roi_wall_heights_m is None else np.asarray(params.roi_wall_heights_m, float),
        )

    @classmethod
    def of_generated(cls, bin: BinParams, T_cam_from_bin: np.ndarray, headroom_m: float = 0.0) -> BinBox:
        """The box of a generated bin (generation/bin.py: its floor's centre at the bin frame's
        origin, z up) seen from a camera at T_cam_from_bin (4, 4). headroom_m > 0: the box reaches
        that far above the rim (parts heaped over it are still the bin's), its walls as high as
        the rim."""
        half = np.array([bin.inner_x_m / 2.0, bin.inner_y_m / 2.0])
        return cls(
            np.asarray(T_cam_from_bin, dtype=np.float64),
            np.append(-half, 0.0),
            np.append(half, bin.wall_height_m + headroom_m),
            np.full(4, bin.wall_height_m) if headroom_m > 0 else None,
        )

    def as_import_settings(self) -> dict[str, object]:
        """The import_capture keys that crop to this box."""
        return {
            "T_cam_from_roi": [[round(float(x), 9) for x in row] for row in self.T_cam_from_bin],
            "roi_min_m": [round(float(x), 4) for x in self.inner_min_m],
            "roi_max_m": [round(float(x), 4) for x in self.inner_max_m],
            "roi_wall_heights_m": None
            if self.wall_heights_m is None
            else [round(float(x), 4) for x in self.wall_heights_m],
        }

    def wall_side(self, plane: np.ndarray) -> int | None:
        """Which of the box's sides (an index into WALL_SIDES) a plane (4,) a, b, c, d (unit normal,
        camera frame) stands at: parallel to that side and near it (WALL_OUTER_SHARE); None when
        it stands at none."""
        T = np.asarray(self.T_cam_from_bin, dtype=np.float64)
        lo, hi = np.asarray(self.inner_min_m, float), np.asarray(self.inner_max_m, float)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        centre_cam = T[:3, :3] @ centre + T[:3, 3]
        n = np.asarray(plane[:3], float)
        for axis in (0, 1):
            along = float(n @ T[:3, axis])
            if abs(along) < np.cos(np.radians(BIN_PLANE_AGREEMENT_DEG)):
                continue
            # Where the plane crosses the axis through the box's centre, from the centre.
            offset = -float(n @ centre_cam + plane[3]) / along
            if abs(offset) >= (1.0 - WALL_OUTER_SHARE) * half[axis]:
                return 2 * axis + int(offset > 0)
        return None

    def wall_top_m(self, side: int) -> float:
        """The height of a side's wall (an index into WALL_SIDES) in the bin frame: the box's top
        where its wall heights are not given; at most the floor's (inner_min_m z) where it has none."""
        lo, hi = float(self.inner_min_m[2]), float(self.inner_max_m[2])
        return hi if self.wall_heights_m is None else float(np.clip(self.wall_heights_m[side], lo, hi))

    def has_wall(self, side: int) -> bool:
        """Whether the box has a wall at a side (an index into WALL_SIDES): one above its floor."""
        return self.wall_top_m(side) > float(self.inner_min_m[2])

    def is_wall(self, plane: np.ndarray) -> bool:
        """Whether a plane (4,) a, b, c, d (unit normal, camera frame) is one of the box's side
        walls: parallel to a side that has a wall and near it (WALL_OUTER_SHARE)."""
        side = self.wall_side(plane)
        return side is not None and self.has_wall(side)

    def height_m(self, points_cam: np.ndarray) -> np.ndarray:
        """(n,) the height of points (n, 3; camera frame) in the bin frame (its z)."""
        T = np.asarray(self.T_cam_from_bin, dtype=np.float64)
        return (np.asarray(points_cam, float) - T[:3, 3]) @ T[:3, 2]

    def side_planes(self) -> np.ndarray:
        """(w, 4) the planes of its side walls (those it has), camera frame: a, b, c, d with
        a x + b y + c z + d = 0, the unit normal facing into the bin."""
        T = np.asarray(self.T_cam_from_bin, dtype=np.float64)
        lo, hi = np.asarray(self.inner_min_m, float), np.asarray(self.inner_max_m, float)
        planes = []
        sides = ((0, lo[0], 1.0), (0, hi[0], -1.0), (1, lo[1], 1.0), (1, hi[1], -1.0))  # WALL_SIDES' order
        for k, (axis, value, inward) in enumerate(sides):
            if not self.has_wall(k):
                continue
            n = inward * T[:3, axis]
            point = T[:3, :3] @ (np.eye(3)[axis] * value) + T[:3, 3]
            planes.append(np.append(n, -n @ point))
        return np.array(planes).reshape(-1, 4)

    def surface_points(self, spacing_m: float) -> np.ndarray:
        """(n, 3) camera frame: points on the inner faces of the walls and the floor."""
        return self.surface(spacing_m)[0]

    def surface(self, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 3) on the inner faces of the walls (as high as they are) and the floor, about
        spacing_m apart, and their faces' unit normals (n, 3), facing into the bin; camera frame."""
        lo, hi = np.asarray(self.inner_min_m, float), np.asarray(self.inner_max_m, float)
        tops = [self.wall_top_m(k) for k in range(4)]

        def steps(a: float, b: float) -> np.ndarray:
            return np.linspace(a, b, max(2, int(np.ceil((b - a) / spacing_m)) + 1))

        faces, normals = [], []
        for fixed in range(3):
            others = [k for k in range(3) if k != fixed]
            for value, inward in ((lo[fixed], 1.0),) if fixed == 2 else ((lo[fixed], 1.0), (hi[fixed], -1.0)):  # no lid
                top = hi[2] if fixed == 2 else tops[2 * fixed + (inward < 0)]
                if top <= lo[2]:
                    continue  # no wall on this side
                spans = [steps(lo[k], top if k == 2 else hi[k]) for k in others]
                A, B = np.meshgrid(*spans, indexing="ij")
                f = np.empty((A.size, 3))
                f[:, fixed], f[:, others[0]], f[:, others[1]] = value, A.ravel(), B.ravel()
                faces.append(f)
                normals.append(np.tile(inward * np.eye(3)[fixed], (A.size, 1)))
        R = np.asarray(self.T_cam_from_bin, dtype=np.float64)[:3, :3]
        return transform_points(self.T_cam_from_bin, np.concatenate(faces)), np.concatenate(normals) @ R.T


def support_frame(
    floor_plane: np.ndarray, bin_box: BinBox | None = None, agreement_m: float = BIN_PLANE_AGREEMENT_M
) -> tuple[np.ndarray, np.ndarray | None]:
    """up (3,) unit, camera frame, and the support plane (4,) with that normal (None when there is none).

    With a bin box, up is the box's z axis (toward the camera) and the plane its floor (bin
    frame z = 0), unless the plane found in the capture agrees with that floor within
    BIN_PLANE_AGREEMENT_DEG and agreement_m (metres, at the box's origin): on an oblique view the
    plane found may be the table beside the box, or a wall. Without one, the plane found, else the
    camera's -z.
    """
    plane = np.asarray(floor_plane, dtype=np.float64)
    found = None
    if plane.shape == (4,) and np.all(np.isfinite(plane)):
        n = plane[:3] / np.linalg.norm(plane[:3])
        d = plane[3] / np.linalg.norm(plane[:3])
        if d < 0:  # the normal toward the camera (origin): n . 0 + d > 0
            n, d = -n, -d
        found = np.append(n, d)
    if bin_box is not None:
        T = np.asarray(bin_box.T_cam_from_bin, dtype=np.float64)
        up, origin = T[:3, 2] / np.linalg.norm(T[:3, 2]), T[:3, 3]
        if -up @ origin < 0:  # toward the camera
            up = -up
        box_plane = np.append(up, -up @ origin)
        if (
            found is not None
            and found[:3] @ up >= np.cos(np.radians(BIN_PLANE_AGREEMENT_DEG))
            and abs(found[:3] @ origin + found[3]) <= agreement_m
        ):
            return found[:3], found
        return up, box_plane
    if found is not None:
        return found[:3], found
    return np.array([0.0, 0.0, -1.0]), None
