"""Capture formats, the real scans in ../shared/data, and capture through a fake Zivid camera."""

import datetime
import json
import types

import numpy as np
import open3d as o3d
import pytest
from PIL import Image

from binpick.errors import InputError, MissingDependencyError
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.pcd import load_pcd, save_pcd
from binpick.io.ply import PointCloudData
from binpick.io.zdf import save_zdf_v1
from binpick.scene.cleaning import clean_capture

from settings import PARAMS, changed


def _organized(H=12, W=16):
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-100, -80, 400], [100, 80, 600], (H * W, 3)).astype(np.float32)
    xyz[rng.random(H * W) < 0.2] = np.nan
    rgb = rng.integers(0, 256, (H * W, 3)).astype(np.uint8)
    return xyz, rgb


def test_pcd_binary_roundtrip_organized(tmp_path):
    xyz, rgb = _organized()
    save_pcd(tmp_path / "c.pcd", PointCloudData(xyz, rgb, None, (12, 16)))
    cap = load_capture(tmp_path / "c.pcd", ImportOptions("mm"))
    assert cap.shape == (12, 16) and np.array_equal(cap.rgb, rgb)
    assert np.allclose(cap.xyz_m, xyz / 1000, equal_nan=True)


@pytest.mark.parametrize("compressed,ascii", [(True, False), (False, True)])
def test_pcd_written_by_open3d(tmp_path, compressed, ascii):
    pts = np.random.default_rng(1).uniform(-1, 1, (500, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (500, 1)))
    o3d.io.write_point_cloud(str(tmp_path / "o.pcd"), pcd, write_ascii=ascii, compressed=compressed)
    data = load_pcd(tmp_path / "o.pcd")
    assert np.allclose(data.xyz, pts, atol=1e-5) and np.allclose(data.normals, [0, 0, 1])


def test_zdf_sdk1_layout_read_without_the_sdk(tmp_path):
    xyz, _ = _organized()
    rgba = np.zeros((12, 16, 4), np.uint8)
    rgba[..., 1] = 200
    save_zdf_v1(tmp_path / "f.zdf", xyz.reshape(12, 16, 3), rgba, np.ones((12, 16), np.float32))
    cap = load_capture(tmp_path / "f.zdf", ImportOptions("mm"))
    assert cap.shape == (12, 16) and (cap.rgb[:, 1] == 200).all()
    assert np.allclose(cap.xyz_m, xyz / 1000, equal_nan=True)


def test_zdf_sdk2_needs_the_zivid_package(tmp_path):
    (tmp_path / "new.zdf").write_bytes(b"ZDF2\x00\x01not hdf5 at all")
    with pytest.raises(MissingDependencyError, match="new.zdf.*pip install zivid"):
        load_capture(tmp_path / "new.zdf", ImportOptions("mm"))


def test_text_columns_and_truncated_last_row(tmp_path):
    rows = ["1.0,2.0,500.0,10,20,30,0.5", "3.0,4.0,510.0,40,50,60,0.7", "5.0,6.0,520.0,70,80"]
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    cap = load_capture(tmp_path / "c.csv", ImportOptions("mm", ("x", "y", "z", "r", "g", "b", "contrast")))
    assert np.allclose(cap.xyz_m, [[0.001, 0.002, 0.5], [0.003, 0.004, 0.51]])
    assert cap.rgb.tolist() == [[10, 20, 30], [40, 50, 60]] and cap.shape is None
    (tmp_path / "c.xyz").write_text("0.1 0.2 0.9\n0.3 0.4 1.0\n")
    cap = load_capture(tmp_path / "c.xyz", ImportOptions("m"))
    assert np.allclose(cap.xyz_m[1], [0.3, 0.4, 1.0])


def test_depth_png_with_intrinsics(tmp_path):
    depth = np.full((20, 30), 1000, np.uint16)
    depth[0, 0] = 0
    Image.fromarray(depth).save(tmp_path / "d.png")
    (tmp_path / "k.json").write_text(json.dumps({"fx": 100.0, "fy": 100.0, "cx": 15.0, "cy": 10.0}))
    cap = load_capture(tmp_path / "d.png", ImportOptions("mm", intrinsics=tmp_path / "k.json"))
    xyz = cap.xyz_m.reshape(20, 30, 3)
    assert np.isnan(xyz[0, 0]).all() and np.allclose(xyz[10, 15], [0, 0, 1.0])
    assert np.allclose(xyz[10, 25], [0.1, 0, 1.0])  # 10 px right of centre at f = 100 px, 1 m
    with pytest.raises(InputError, match="needs intrinsics"):
        load_capture(tmp_path / "d.png", ImportOptions("mm"))


def test_extension_and_content_must_agree(tmp_path):
    Image.fromarray(np.zeros((4, 4), np.uint16)).save(tmp_path / "d.png")
    (tmp_path / "d.ply").write_bytes((tmp_path / "d.png").read_bytes())
    with pytest.raises(InputError, match="extension says ply but the content is depth"):
        load_capture(tmp_path / "d.ply", ImportOptions("mm"))
    (tmp_path / "e.pcd").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        load_capture(tmp_path / "e.pcd", ImportOptions("mm"))


def test_real_zivid_export(shared_data):
    """The Zivid One CSV fragment: its last row is cut (6 of 7 columns). It is the first ~six
    image rows of a frame, a strip in which no support plane is defined: import keeps every
    point, in metres, and reports no plane."""
    cap = load_capture(
        shared_data / "scans/zivid_one_fragment/zivid_one_fragment.csv",
        ImportOptions("mm", ("x", "y", "z", "r", "g", "b", "contrast")),
    )
    assert len(cap.xyz_m) == 10970  # the 10,970 complete rows; the cut last row is skipped
    assert 1.0 < np.median(cap.xyz_m[:, 2]) < 1.3  # about a metre from the camera, in metres
    cloud = clean_capture(cap.xyz_m, cap.rgb, None, PARAMS.import_capture, 0)
    assert np.isnan(cloud.floor_plane).all() and cloud.removed_fraction.sum() == 0
    assert len(cloud.points_m) > 1000 and cloud.rgb.any()


def test_real_rgbd_bin_frame_table_removed_objects_kept(shared_data):
    """IC-BIN: cartons in a box on a table, seen from about a metre. With the sensor's noise
    (the manifest: a plane at about 8 mm) the table goes and the pile stays."""
    scans = shared_data / "scans/icbin_scene1"
    cap = load_capture(scans / "depth/0000.png", ImportOptions("mm", intrinsics=scans / "camera.json"))
    assert cap.shape == (480, 640)
    params = changed(PARAMS.import_capture, plane_threshold_m=0.008, keep_above_plane_m=0.012)
    cloud = clean_capture(cap.xyz_m, None, cap.shape, params, 0)
    a, b, c, d = cloud.floor_plane
    tilt = np.degrees(np.arccos(-c))  # angle between the plane normal and the optical axis
    assert 5 < tilt < 35 and 0.8 < d < 1.1
    assert cloud.removed_fraction[0] > 0.6
    kept = np.zeros(480 * 640, bool)
    kept[cloud.pixel_index] = True
    kept = kept.reshape(480, 640)
    # Pixels of the pile (centre of the image) are kept; open table (lower right) is not.
    pile = np.isfinite(cap.xyz_m.reshape(480, 640, 3)[200:300, 260:420, 2])
    on_grid = kept[200:300, 260:420][pile].mean()
    table = kept[380:460, 330:560].mean()
    assert on_grid > 0.1 and table < 0.01  # the voxel grid keeps one pixel in several


def _fake_zivid(H=6, W=8):
    calls = {}

    class Acquisition:
        def __init__(self, aperture, exposure_time, brightness, gain):
            calls["acquisition"] = (aperture, exposure_time, brightness, gain)

    class Settings:
        def __init__(self, acquisitions):
            calls["n_acquisitions"] = len(acquisitions)

    Settings.Acquisition = Acquisition

    class Cloud:
        def copy_data(self, what):
            if what == "xyz":
                xyz = np.stack([*np.meshgrid(np.arange(W), np.arange(H)), np.full((H, W), 500)], -1).astype(np.float32)
                xyz[0, 0] = np.nan
                return xyz
            return np.full((H, W, 4), 9, np.uint8)

    class Camera:
        def capture(self, settings):
            return types.SimpleNamespace(point_cloud=Cloud)

        def disconnect(self):
            calls["disconnected"] = True

    class Application:
        def connect_camera(self, serial_number=None):
            calls["serial"] = serial_number
            return Camera()

    return types.SimpleNamespace(Application=Application, Settings=Settings), calls


def test_capture_through_a_fake_camera(tmp_path, params):
    from binpick.cell.zivid_camera import grab_to_file

    fake, calls = _fake_zivid()
    settings = params.zivid_camera.model_copy(update={"serial": "ABC", "exposure_time_us": 5000, "aperture": 4.0})
    assert grab_to_file(tmp_path / "cap.ply", settings, zivid=fake) == (6, 8)
    assert calls["serial"] == "ABC" and calls["disconnected"]
    assert calls["acquisition"][:2] == (4.0, datetime.timedelta(microseconds=5000))
    cap = load_capture(tmp_path / "cap.ply", ImportOptions("mm"))
    assert cap.shape == (6, 8) and np.isnan(cap.xyz_m[0]).all() and np.allclose(cap.xyz_m[9], [0.001, 0.001, 0.5])
