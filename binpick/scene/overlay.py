"""Poses drawn over a capture's colour image, for a look by eye beside the rerun recording.

Each pose's model surface points are projected into the image (pinhole K); points the camera
could not see (behind the measured depth at their pixel) are skipped, so a pose drawn where the
part is looks like a tint on it and a pose behind a wall does not hide the wall.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from binpick.errors import InputError
from binpick.io.capture import load_capture
from binpick.io.depth_image import load_intrinsics
from binpick.io.part_model import load_part_model
from binpick.io.picks import load_picks
from binpick.io.poses import load_poses
from binpick.palette import instance_colours
from binpick.registration.visibility import fit_intrinsics

# A model point this far behind the measured depth at its pixel is hidden.
HIDDEN_MARGIN_M = 0.005


def draw_poses(
    image: np.ndarray,
    K: np.ndarray,
    depth_m: np.ndarray | None,
    model_points_m: np.ndarray,
    T_cam_from_model: np.ndarray,
    scores: list[float],
    alpha: float = 0.55,
) -> np.ndarray:
    """The image (H, W, 3) uint8 with each pose's visible model points tinted in its colour.

    model_points_m : (n, 3) model frame; T_cam_from_model : (k, 4, 4); depth_m : (H, W) measured
    depth (NaN = none) or None (every projected point drawn). Returns a new array.
    """
    out = image.astype(np.float32).copy()
    H, W = image.shape[:2]
    poses = np.asarray(T_cam_from_model).reshape(-1, 4, 4)
    palette = instance_colours(max(len(poses), 1))
    for i, T in enumerate(poses):
        p = model_points_m @ T[:3, :3].T + T[:3, 3]
        p = p[p[:, 2] > 1e-6]
        uv = p @ K.T
        u = np.round(uv[:, 0] / uv[:, 2]).astype(np.int64)
        v = np.round(uv[:, 1] / uv[:, 2]).astype(np.int64)
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        u, v, z = u[inside], v[inside], p[inside, 2]
        if depth_m is not None:
            measured = depth_m[v, u]
            u, v = u[~(z > measured + HIDDEN_MARGIN_M)], v[~(z > measured + HIDDEN_MARGIN_M)]
        colour = palette[i].astype(np.float32)
        # Each surface point covers a few pixels at full resolution: a 3 x 3 block.
        mask = np.zeros((H, W), bool)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                mask[np.clip(v + dv, 0, H - 1), np.clip(u + du, 0, W - 1)] = True
        out[mask] = (1 - alpha) * out[mask] + alpha * colour
    return np.clip(out, 0, 255).astype(np.uint8)


def label_poses(image: np.ndarray, K: np.ndarray, T_cam_from_model: np.ndarray, scores: list[float]) -> np.ndarray:
    """Write each pose's index and score at its model origin's pixel."""

    img = Image.fromarray(image)
    draw = ImageDraw.Draw(img)
    poses = np.asarray(T_cam_from_model).reshape(-1, 4, 4)
    palette = instance_colours(max(len(poses), 1))
    for i, (T, s) in enumerate(zip(poses, scores, strict=True)):
        if T[2, 3] <= 0:
            continue
        uvw = K @ T[:3, 3]
        x, y = uvw[0] / uvw[2], uvw[1] / uvw[2]
        draw.text((x + 1, y + 1), f"{i}:{s:.2f}", fill=(0, 0, 0))
        draw.text((x, y), f"{i}:{s:.2f}", fill=tuple(int(c) for c in palette[i]))
    return np.asarray(img)


def capture_image(xyz_m: np.ndarray, rgb: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """An organized capture as an image (H, W, 3) uint8: its colours, or its depth shaded (near
    bright, far dark, no measurement black) when it has none.

    xyz_m : (H * W, 3) camera frame, metres, NaN where nothing was measured; rgb : (H * W, 3) or None.
    """
    H, W = shape
    if rgb is not None and np.any(rgb):
        return np.asarray(rgb, dtype=np.uint8).reshape(H, W, 3)
    z = np.asarray(xyz_m, dtype=np.float64).reshape(H, W, 3)[..., 2]
    ok = np.isfinite(z)
    lo, hi = (float(np.nanmin(z)), float(np.nanmax(z))) if ok.any() else (0.0, 1.0)
    grey = np.where(ok, 230 - 180 * (np.nan_to_num(z, nan=hi) - lo) / max(hi - lo, 1e-9), 0).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def draw_pick(image: np.ndarray, K: np.ndarray, T_cam_from_pregrasp: np.ndarray, T_cam_from_grasp: np.ndarray):
    """The image (H, W, 3) uint8 with a pick drawn: a ring at the grasp's tool centre point and
    the approach from the pre-grasp's, in yellow over black so it shows on any part's tint.
    K : (3, 3) pinhole; the poses (4, 4), camera frame, metres. Returns a new array."""

    img = Image.fromarray(image)
    draw = ImageDraw.Draw(img)
    ends = []
    for T in (T_cam_from_pregrasp, T_cam_from_grasp):
        p = np.asarray(T, dtype=float)[:3, 3]
        if p[2] <= 0:
            return np.asarray(img)
        uvw = K @ p
        ends.append((float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])))
    (x0, y0), (x1, y1) = ends
    r = max(5.0, 0.015 * max(image.shape[:2]))
    for colour, width in (((0, 0, 0), 7), ((255, 220, 0), 3)):
        draw.line([(x0, y0), (x1, y1)], fill=colour, width=width)
        draw.ellipse([x1 - r, y1 - r, x1 + r, y1 + r], outline=colour, width=width)
    return np.asarray(img)


def overlay_capture(capture_path, options, poses_path, part_model_path, image_path=None, picks_path=None) -> np.ndarray:
    """The overlay image (H, W, 3) uint8 of a processed capture: its colour image (or `image_path`,
    or depth shading when it has no colour) with its poses drawn, and the first pick of
    `picks_path` (a picks.json) when given. The capture must be organized."""

    capture = load_capture(capture_path, options)
    if capture.shape is None:
        raise InputError(capture_path, "not an organized capture (one point per pixel): there is no image to draw on")
    H, W = capture.shape
    xyz = capture.xyz_m.reshape(-1, 3)
    K = (
        load_intrinsics(options.intrinsics, (H, W)) if options.intrinsics is not None else fit_intrinsics(xyz, (H, W))
    ).K
    if image_path is not None:
        try:
            image = np.asarray(Image.open(Path(image_path)).convert("RGB"))
        except OSError as exc:
            raise InputError(image_path, f"not a readable image ({exc})") from None
        if image.shape[:2] != (H, W):
            raise InputError(image_path, f"is {image.shape[1]} x {image.shape[0]}, the capture {W} x {H}")
    else:
        image = capture_image(xyz, capture.rgb, (H, W))
    _, poses = load_poses(poses_path)
    part = load_part_model(part_model_path)
    T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
    scores = [p.score for p in poses]
    first = None
    if picks_path is not None:
        picks = load_picks(picks_path)["picks"]
        first = (np.asarray(picks[0]["camera"]["pregrasp"]), np.asarray(picks[0]["camera"]["grasp"])) if picks else None
    depth = xyz[:, 2].reshape(H, W)
    return draw_answer(image, K, depth, part.points_m.astype(np.float64), T, scores, first)


def draw_answer(
    image: np.ndarray,
    K: np.ndarray,
    depth_m: np.ndarray | None,
    model_points_m: np.ndarray,
    T_cam_from_model: np.ndarray,
    scores: list[float],
    first_pick: tuple[np.ndarray, np.ndarray] | None,
) -> np.ndarray:
    """The image (H, W, 3) uint8 with the poses tinted and labelled (draw_poses, label_poses) and
    the first pick drawn (draw_pick; first_pick: its T_cam_from_pregrasp and T_cam_from_grasp, or
    None when nothing was picked). Returns a new array."""
    drawn = draw_poses(image, K, depth_m, model_points_m, T_cam_from_model, scores)
    drawn = label_poses(drawn, K, T_cam_from_model, scores)
    return draw_pick(drawn, K, *first_pick) if first_pick is not None else drawn


def pick_overlay(
    xyz_m: np.ndarray,
    rgb: np.ndarray | None,
    shape: tuple[int, int],
    model_points_m: np.ndarray,
    T_cam_from_model: np.ndarray,
    scores: list[float],
    first_pick: tuple[np.ndarray, np.ndarray] | None,
    max_width_px: int = 1024,
) -> np.ndarray:
    """One answered capture for the operator: its image (colour, or shaded depth) with the poses
    and the chosen pick drawn (draw_answer), at most max_width_px wide (H', W', 3) uint8.

    xyz_m : (H * W, 3) organized capture, camera frame, metres; model_points_m : (n, 3) model frame;
    T_cam_from_model : (k, 4, 4); first_pick: the pick's T_cam_from_pregrasp and T_cam_from_grasp
    (4, 4), or None when nothing was picked.
    """

    H, W = shape
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    K = fit_intrinsics(xyz, (H, W)).K
    T = np.asarray(T_cam_from_model, dtype=float).reshape(-1, 4, 4)
    image = capture_image(xyz, rgb, shape)
    drawn = draw_answer(image, K, xyz[:, 2].reshape(H, W), model_points_m, T, scores, first_pick)
    if W > max_width_px:
        drawn = np.asarray(
            Image.fromarray(drawn).resize((max_width_px, round(H * max_width_px / W)), Image.Resampling.BILINEAR)
        )
    return drawn
