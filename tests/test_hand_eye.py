"""Hand-eye calibration on synthetic pose pairs with a known answer, noise and ill-posed sets,
and board detection in a rendered checkerboard image."""

import numpy as np
import pytest

from binpick.cell.hand_eye import board_points, board_pose, solve_hand_eye
from binpick.errors import BinpickError
from binpick.geometry.transforms import axis_angle_to_R, invert_T, make_T

pytest.importorskip("cv2", reason="hand-eye calibration uses OpenCV (pip install -e .[bench])")


def _random_T(rng, angle_deg, scale_m):
    axis = rng.normal(size=3)
    return make_T(
        axis_angle_to_R(axis / np.linalg.norm(axis), np.radians(rng.uniform(-angle_deg, angle_deg))),
        rng.normal(0, scale_m, 3),
    )


def _noisy(T, rng, mm, deg):
    axis = rng.normal(size=3)
    return (
        make_T(
            axis_angle_to_R(axis / np.linalg.norm(axis), np.radians(rng.normal(0, deg))), rng.normal(0, mm / 1000, 3)
        )
        @ T
    )


def _angle_deg(R):
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("setup", ["eye_to_hand", "eye_in_hand"])
def test_the_known_camera_pose_is_recovered_under_noise(setup):
    rng = np.random.default_rng(0)
    X = make_T(
        axis_angle_to_R(np.array([1.0, 0.2, 0.0]) / np.linalg.norm([1.0, 0.2, 0.0]), np.radians(150)),
        np.array([0.6, -0.1, 1.2]),
    )
    board = _random_T(rng, 30, 0.1)
    flange = np.array([make_T(np.eye(3), np.array([0.5, 0.0, 0.4])) @ _random_T(rng, 35, 0.08) for _ in range(12)])
    if setup == "eye_to_hand":  # X = T_base_from_cam, board = T_flange_from_target
        cam_target = np.array([invert_T(X) @ f @ board for f in flange])
    else:  # X = T_flange_from_cam, board = T_base_from_target
        cam_target = np.array([invert_T(X) @ invert_T(f) @ board for f in flange])
    noisy = np.array([_noisy(T, rng, 0.5, 0.1) for T in cam_target])
    result = solve_hand_eye(flange, noisy, setup)
    assert np.linalg.norm(result.T[:3, 3] - X[:3, 3]) < 0.003
    assert _angle_deg(result.T[:3, :3].T @ X[:3, :3]) < 0.3
    assert 0.1 < result.residual_mm_median < 3.0 and result.residual_deg_median < 0.5
    exact = solve_hand_eye(flange, cam_target, setup)
    assert np.allclose(exact.T, X, atol=1e-6) and exact.residual_mm_max < 1e-3


def test_ill_posed_sets_are_refused():
    rng = np.random.default_rng(1)
    some = np.array([_random_T(rng, 30, 0.1) for _ in range(5)])
    with pytest.raises(BinpickError, match="at least 3 robot poses"):
        solve_hand_eye(some[:2], some[:2], "eye_to_hand")
    shifted = np.array([make_T(np.eye(3), rng.normal(0, 0.1, 3)) for _ in range(5)])
    with pytest.raises(BinpickError, match="turns by less than"):
        solve_hand_eye(shifted, some, "eye_to_hand")
    one_axis = np.array(
        [
            make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(a)), rng.normal(0, 0.1, 3))
            for a in (0, 20, 45, 70, 90)
        ]
    )
    with pytest.raises(BinpickError, match="one axis only"):
        solve_hand_eye(one_axis, some, "eye_to_hand")
    with pytest.raises(BinpickError, match="one of each"):
        solve_hand_eye(some, some[:4], "eye_to_hand")


def _render_board(T, pattern, square, H=480, W=640, f=600.0):
    """Grey image (H, W) uint8 and organized cloud (H, W, 3) metres of a checkerboard whose frame
    is at T (camera frame): a plane with squares from -1 to the pattern's size."""
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u, float)], -1)
    n, p0 = T[:3, 2], T[:3, 3]
    t = (p0 @ n) / (rays @ n)
    xyz = rays * t[..., None]
    local = (xyz - p0) @ T[:3, :3]  # board frame
    # Squares from -1 to cols: the inner corners are at integer multiples of the square.
    i, j = np.floor(local[..., 0] / square), np.floor(local[..., 1] / square)
    on = (i >= -1) & (i <= pattern[0] - 1) & (j >= -1) & (j <= pattern[1] - 1)
    image = np.where(on, np.where((i + j) % 2 == 0, 20, 235), 128).astype(np.uint8)
    return image, xyz, K


def test_the_board_pose_is_found_in_a_rendered_image():
    """A 9 x 6 checkerboard of 25 mm squares rendered by ray casting at a known pose: found in the
    colour image alone (solvePnP) and with the organized cloud (rigid fit of the corners)."""
    pattern, square = (9, 6), 0.025
    T = make_T(
        axis_angle_to_R(np.array([1.0, 0.3, 0.1]) / np.linalg.norm([1.0, 0.3, 0.1]), np.radians(20)),
        np.array([-0.1, -0.06, 0.6]),
    )
    image, xyz, K = _render_board(T, pattern, square)
    found = board_pose(image, pattern, square, K)
    assert found is not None
    assert np.linalg.norm(found[:3, 3] - T[:3, 3]) < 0.003 and _angle_deg(found[:3, :3].T @ T[:3, :3]) < 0.5
    cloud = board_pose(np.repeat(image[..., None], 3, -1), pattern, square, K, xyz.astype(np.float32))
    assert cloud is not None and np.linalg.norm(cloud[:3, 3] - T[:3, 3]) < 0.003
    assert board_points(pattern, square).shape == (54, 3)


def test_the_command_calibrates_from_captures_of_a_board_on_the_flange(tmp_path):
    """binpick hand-eye on organized PLY captures (colour and points) of a board carried by the
    robot: the camera's pose in the base frame, and a one-line refusal of an ill-posed set."""
    import json
    import subprocess
    import sys

    from binpick.io.ply import PointCloudData, save_ply
    from tests.conftest import ROOT

    rng = np.random.default_rng(3)
    pattern, square = (7, 6), 0.03  # odd by even: the corner order cannot flip by half a turn
    T_base_cam = make_T(
        axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(180)), np.array([0.4, 0.0, 1.0])
    )  # looking down
    T_flange_board = make_T(np.eye(3), np.array([-0.09, -0.06, 0.02]))
    pairs = []
    for k in range(6):
        axis = rng.normal(size=3)
        tilt = axis_angle_to_R(axis / np.linalg.norm(axis), np.radians(rng.uniform(8, 20)))
        T_base_flange = make_T(tilt, np.array([0.4, 0.0, 0.45]) + rng.normal(0, 0.03, 3))
        T_cam_board = invert_T(T_base_cam) @ T_base_flange @ T_flange_board
        image, xyz, _ = _render_board(T_cam_board, pattern, square)
        H, W = image.shape
        save_ply(
            tmp_path / f"cap{k}.ply",
            PointCloudData(
                xyz.reshape(-1, 3).astype(np.float32) * 1000.0, np.repeat(image.reshape(-1, 1), 3, 1), None, (H, W)
            ),
        )
        pairs.append({"capture": f"cap{k}.ply", "T_base_from_flange": T_base_flange.tolist()})
    (tmp_path / "pairs.json").write_text(json.dumps({"pairs": pairs}))
    run = [
        sys.executable,
        "-m",
        "flows.cli",
        "hand-eye",
        "--pairs",
        str(tmp_path / "pairs.json"),
        "--pattern",
        "7x6",
        "--square-mm",
        "30",
        "--out",
        str(tmp_path / "he.json"),
    ]
    proc = subprocess.run(run, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    found = np.asarray(json.loads((tmp_path / "he.json").read_text())["T_base_from_cam"])
    assert (
        np.linalg.norm(found[:3, 3] - T_base_cam[:3, 3]) < 0.005
        and _angle_deg(found[:3, :3].T @ T_base_cam[:3, :3]) < 0.5
    )
    # --apply: the result becomes the pick setting, comments kept, the file still valid.
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    proc = subprocess.run(
        [*run, "--apply", "--params", str(tmp_path / "params.yaml")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    from binpick.params import load_params

    assert np.allclose(load_params(tmp_path / "params.yaml").pick.T_base_from_cam, found, atol=1e-8)
    assert "# grasps and picks" in (tmp_path / "params.yaml").read_text()
    (tmp_path / "pairs.json").write_text(json.dumps({"pairs": pairs[:2]}))
    proc = subprocess.run(run, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "at least 3 robot poses" in proc.stderr
