"""rerun recordings (`.rrd`) of a scene run: the scene, segments coloured by instance, the CAD
mesh at every estimated pose, ground truth beside it. Entity paths mirror the frames: everything
lives under `camera/` in the camera frame (RDF: x right, y down, z forward)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from binpick.io.atomic import atomic_path
from binpick.io.cloud import CleanCloud
from binpick.io.part_model import PartModel
from binpick.io.poses import PartPose
from binpick.palette import UNLABELLED_GREY, instance_colours, instance_rgb

TRUTH_COLOUR = np.array([60, 200, 90, 90], np.uint8)
PLANE_COLOUR = np.array([90, 120, 200, 70], np.uint8)


def write_scene_recording(
    path: Path,
    name: str,
    cloud: CleanCloud,
    labels: np.ndarray,
    part: PartModel,
    estimates: list[PartPose],
    truth: list[PartPose] | None,
    timings_s: dict[str, float],
) -> None:
    import rerun as rr

    rec = rr.RecordingStream("binpick", recording_id=f"scene-{name}")
    with atomic_path(path) as tmp:
        rec.save(str(tmp))  # to a file, never a viewer
        rec.log("camera", rr.ViewCoordinates.RDF, static=True)
        rec.log("camera/scene", rr.Points3D(cloud.points_m, colors=cloud.rgb, radii=0.0008))
        n = int(labels.max()) + 1 if len(labels) and labels.max() >= 0 else 0
        palette = instance_colours(max(n, 1))
        rec.log(
            "camera/segments", rr.Points3D(cloud.points_m, colors=instance_rgb(labels), radii=0.001, class_ids=labels)
        )
        if np.isfinite(cloud.floor_plane).all():
            a, b, c, d = cloud.floor_plane
            quad = plane_quad(cloud.floor_plane, cloud.points_m)
            if quad is not None:
                rec.log(
                    "camera/floor_plane",
                    rr.Mesh3D(
                        vertex_positions=quad, triangle_indices=[[0, 1, 2], [0, 2, 3]], albedo_factor=PLANE_COLOUR
                    ),
                    static=True,
                )
            rec.log(
                "camera/floor_plane/equation",
                rr.TextDocument(f"removed floor plane: {a:.4f} x + {b:.4f} y + {c:.4f} z + {d:.4f} = 0 (metres)"),
                static=True,
            )
        for k, pose in enumerate(estimates):
            colour = palette[pose.segment % len(palette)] if pose.segment >= 0 else UNLABELLED_GREY
            log_part(rec, f"camera/parts/{k}", pose, part, np.append(colour, 255).astype(np.uint8))
        for k, pose in enumerate(truth or []):
            log_part(rec, f"camera/truth/{k}", pose, part, TRUTH_COLOUR)
        rec.log("timings", rr.TextDocument("\n".join(f"{k}: {v:.3f} s" for k, v in timings_s.items())), static=True)
        rec.flush()
        rec.disconnect()


def plane_quad(plane: np.ndarray, points_m: np.ndarray, margin_m: float = 0.02) -> np.ndarray | None:
    """(4, 3) float32 corners of the plane a x + b y + c z + d = 0 (camera frame) under the
    points' x/y extent plus a margin, for drawing; None when the plane is edge-on to the camera."""
    a, b, c, d = (float(v) for v in plane)
    if abs(c) < 1e-3 or len(points_m) == 0:
        return None
    lo, hi = points_m[:, :2].min(axis=0) - margin_m, points_m[:, :2].max(axis=0) + margin_m
    xy = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    z = -(a * xy[:, 0] + b * xy[:, 1] + d) / c
    return np.column_stack([xy, z]).astype(np.float32)


def log_part(rec, entity: str, pose: PartPose, part: PartModel, rgba: np.ndarray) -> None:
    import rerun as rr

    T = pose.T_cam_from_model
    rec.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log(
        f"{entity}/mesh",
        rr.Mesh3D(
            vertex_positions=part.mesh_vertices_m.astype(np.float32),
            triangle_indices=part.mesh_faces.astype(np.uint32),
            albedo_factor=rgba,
        ),
    )
    rec.log(f"{entity}/score", rr.TextDocument(f"score {pose.score:.3f}"))


class TrainingRecording:
    """Sample predictions during training: a few fixed validation views, segmented by the network
    after chosen epochs (timeline `epoch`), beside their ground-truth instances."""

    def __init__(self, path: Path, part: str, views: list[tuple[np.ndarray, np.ndarray]]):
        import rerun as rr

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("binpick", recording_id=f"train-{part}")
        self.rec.save(str(self.path))  # to a file, never a viewer
        self.rec.log("views", rr.ViewCoordinates.RDF, static=True)
        self.views = views
        for i, (points, labels) in enumerate(views):
            self.rec.log(
                f"views/{i}/truth", rr.Points3D(points, colors=instance_rgb(labels), radii=0.0008), static=True
            )

    def log_epoch(self, epoch: int, predictions: list[np.ndarray], metrics: dict[str, float]) -> None:
        import rerun as rr

        self.rec.set_time("epoch", sequence=epoch)
        for i, ((points, _), labels) in enumerate(zip(self.views, predictions, strict=False)):
            self.rec.log(f"views/{i}/prediction", rr.Points3D(points, colors=instance_rgb(labels), radii=0.0008))
        for key in ("train_loss", "val_loss"):
            if key in metrics:
                self.rec.log(f"loss/{key}", rr.Scalars(metrics[key]))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def write_bin_recording(
    path: Path,
    name: str,
    points_m: np.ndarray,
    rgb: np.ndarray | None,
    inside: np.ndarray,
    T_cam_from_bin: np.ndarray,
    inner_min_m: np.ndarray,
    inner_max_m: np.ndarray,
) -> None:
    """`binpick fit-bin`'s recording: the capture (points inside the fitted box in colour, the
    rest grey) and the box, camera frame, for the user to check before keeping the box."""
    import rerun as rr

    from binpick.geometry.transforms import transform_points

    rec = rr.RecordingStream("binpick", recording_id=f"bin-{name}")
    with atomic_path(path) as tmp:
        rec.save(str(tmp))
        rec.log("camera", rr.ViewCoordinates.RDF, static=True)
        colours = np.asarray(rgb if rgb is not None else np.full((len(points_m), 3), 200), dtype=np.uint8).copy()
        colours[~inside] = 90
        rec.log("camera/capture", rr.Points3D(points_m, colors=colours, radii=0.001), static=True)
        lo, hi = np.asarray(inner_min_m), np.asarray(inner_max_m)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        c = transform_points(T_cam_from_bin, corners)
        edges = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
        rec.log(
            "camera/bin_box",
            rr.LineStrips3D([[c[a], c[b]] for a, b in edges], colors=[255, 160, 0], radii=0.0015),
            static=True,
        )
        rec.log(
            "camera/bin_box/size",
            rr.TextDocument(
                f"inner box {1000 * (hi[0] - lo[0]):.0f} x {1000 * (hi[1] - lo[1]):.0f} mm, "
                f"{1000 * lo[2]:.0f}-{1000 * hi[2]:.0f} mm above the support plane"
            ),
            static=True,
        )
        rec.disconnect()
