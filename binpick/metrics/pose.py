"""6D pose error metrics (BOP conventions), symmetry-aware where the part has symmetries.

Poses are (4, 4) T_cam_from_model in metres; model points (n, 3) in the model frame, metres;
symmetries (m, 4, 4) transforms of the model frame onto itself (identity included).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from binpick.geometry.transforms import rotation_angle_deg, transform_points


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray, symmetries: np.ndarray | None = None) -> float:
    """Smallest angle between the estimated rotation and any symmetric twin of the true one."""
    syms = np.eye(4)[None] if symmetries is None else symmetries
    R_gt = T_gt[:3, :3] @ syms[:, :3, :3]  # (m, 3, 3)
    return float(rotation_angle_deg(np.broadcast_to(T_est[:3, :3], R_gt.shape), R_gt).min())


def translation_error_m(T_est: np.ndarray, T_gt: np.ndarray, centre_m: np.ndarray | None = None) -> float:
    """Distance between the estimated and the true position of the part's centre (model frame
    point `centre_m`, default the model origin). A CAD origin can lie far from the part, where
    it would turn a small rotation error into a large 'translation' error; symmetries leave the
    centre where it is."""
    c = np.zeros(3) if centre_m is None else np.asarray(centre_m, dtype=np.float64)
    return float(np.linalg.norm((T_est[:3, :3] @ c + T_est[:3, 3]) - (T_gt[:3, :3] @ c + T_gt[:3, 3])))


def add(T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray) -> float:
    """Average distance of corresponding model points (metres)."""
    return float(
        np.linalg.norm(transform_points(T_est, model_points) - transform_points(T_gt, model_points), axis=1).mean()
    )


def add_s(T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray) -> float:
    """Average distance from each estimated model point to the closest true one (for symmetric parts)."""
    d, _ = cKDTree(transform_points(T_gt, model_points)).query(transform_points(T_est, model_points))
    return float(d.mean())


def mssd(T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray, symmetries: np.ndarray) -> float:
    """Maximum symmetry-aware surface distance (BOP): min over symmetries of the max point distance."""
    est = transform_points(T_est, model_points)
    best = np.inf
    for S in symmetries:
        best = min(best, float(np.linalg.norm(est - transform_points(T_gt @ S, model_points), axis=1).max()))
    return best


def pose_errors(
    T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray, symmetries: np.ndarray, diameter_m: float
) -> dict[str, float]:
    """All errors of one estimate. ADD-S replaces ADD for symmetric parts (more than one symmetry);
    the translation error is that of the centre of the model points."""
    symmetric = len(symmetries) > 1
    add_value = add_s(T_est, T_gt, model_points) if symmetric else add(T_est, T_gt, model_points)
    rot = rotation_error_deg(T_est, T_gt, symmetries)
    trans = translation_error_m(T_est, T_gt, model_points.mean(axis=0))
    return {
        "rot_err_deg": rot,
        "trans_err_mm": 1000.0 * trans,
        "add_mm": 1000.0 * add_value,
        "mssd_mm": 1000.0 * mssd(T_est, T_gt, model_points, symmetries),
        "add_ok": float(add_value < 0.1 * diameter_m),
        "ok_5deg_5mm": float(rot < 5.0 and trans < 0.005),
    }


# Ground-truth parts less visible than this are not expected to be found (a robot would not pick
# them either); they still may be matched.
MIN_VISIBLE_FRACTION = 0.5


def scene_pose_metrics(
    T_est: np.ndarray,
    T_gt: np.ndarray,
    visible_fraction: np.ndarray,
    model_points: np.ndarray,
    symmetries: np.ndarray,
    diameter_m: float,
) -> tuple[dict[str, float], list[dict[str, float]]]:
    """Match estimates to ground truth one-to-one (Hungarian on centre distance, accepted below
    half a diameter) and summarise.

    T_est (e, 4, 4), T_gt (g, 4, 4), visible_fraction (g,). Returns the summary and per-estimate
    errors (empty dict where unmatched). Recall counts ground truth with at least
    MIN_VISIBLE_FRACTION visible.
    """
    from scipy.optimize import linear_sum_assignment

    centre = model_points.mean(axis=0)
    per_est: list[dict[str, float]] = [{} for _ in range(len(T_est))]
    pickable = visible_fraction >= MIN_VISIBLE_FRACTION
    if len(T_est) and len(T_gt):
        c_est = np.stack([T[:3, :3] @ centre + T[:3, 3] for T in T_est])
        c_gt = np.stack([T[:3, :3] @ centre + T[:3, 3] for T in T_gt])
        cost = np.linalg.norm(c_est[:, None] - c_gt[None], axis=2)
        for e, g in zip(*linear_sum_assignment(cost), strict=False):
            if cost[e, g] < 0.5 * diameter_m:
                per_est[e] = {
                    **pose_errors(T_est[e], T_gt[g], model_points, symmetries, diameter_m),
                    "gt_index": float(g),
                }
    matched = [m for m in per_est if m]
    found_ok = {int(m["gt_index"]) for m in matched if m["add_ok"]}
    n_pickable = int(pickable.sum())
    summary = {
        "n_estimates": float(len(T_est)),
        "n_ground_truth": float(len(T_gt)),
        "n_pickable": float(n_pickable),
        "pose_precision": float(len([m for m in matched if m["add_ok"]]) / len(T_est)) if len(T_est) else 0.0,
        "pose_recall": float(sum(1 for g in found_ok if pickable[g]) / n_pickable) if n_pickable else 0.0,
        "rot_err_deg_median": float(np.median([m["rot_err_deg"] for m in matched])) if matched else float("nan"),
        "trans_err_mm_median": float(np.median([m["trans_err_mm"] for m in matched])) if matched else float("nan"),
        "add_mm_median": float(np.median([m["add_mm"] for m in matched])) if matched else float("nan"),
    }
    return summary, per_est
