"""The pinhole camera: projection and back-projection recover each other's known answers."""

from __future__ import annotations

import numpy as np

from binpick.geometry.camera import PinholeCamera


def test_back_projected_pixels_project_to_themselves():
    camera = PinholeCamera(40, 30, 50.0, 55.0, 19.2, 14.7)
    depth = np.random.default_rng(0).uniform(0.4, 1.2, camera.shape).astype(np.float32)
    uv = camera.project(camera.back_project(depth))
    v, u = np.mgrid[0:30, 0:40]
    assert np.allclose(uv, np.column_stack([u.ravel(), v.ravel()]), atol=1e-3)
    assert np.allclose(camera.back_project(depth)[:, 2], depth.ravel())


def test_a_binned_camera_sees_a_point_at_the_binned_pixel():
    camera = PinholeCamera(640, 480, 600.0, 600.0, 319.5, 239.5)
    point = np.array([[0.05, -0.03, 0.8]])
    u, v = camera.project(point)[0]
    u2, v2 = camera.downscaled(2).project(point)[0]
    # Pixels 2k and 2k + 1 bin into k: centres (2k + 0.5) map to k.
    assert np.allclose([u2, v2], [(u - 0.5) / 2, (v - 0.5) / 2])
    assert camera.downscaled(2).shape == (240, 320)


def test_intrinsics_of_another_resolution_are_named():
    assert "another resolution" in PinholeCamera(64, 48, 50.0, 50.0, 320.0, 240.0).fits((48, 64))
    assert PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5).fits((48, 64)) is None
    assert "positive" in PinholeCamera(64, 48, -1.0, 50.0, 31.5, 23.5).fits((48, 64))
    assert np.isnan(PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5).project(np.array([[0.0, 0.0, -1.0]]))).all()
