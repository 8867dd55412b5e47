"""AbsolutePoseProblem construction: the query/reference rays of every camera model."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.robust.problem import _rays

W, H = 640, 480


@pytest.mark.parametrize(
    "camera",
    [
        Camera("SIMPLE_PINHOLE", W, H, (500.0, 320.0, 240.0)),
        Camera("OPENCV", W, H, (510.0, 490.0, 321.5, 238.25, 0.0, 0.0, 0.0, 0.0)),
        Camera("SIMPLE_RADIAL", W, H, (505.0, 321.5, 238.25, -0.12)),
        Camera("RADIAL", W, H, (505.0, 321.5, 238.25, -0.25, 0.08)),
        Camera("OPENCV", W, H, (510.0, 490.0, 321.5, 238.25, -0.2, 0.05, 1e-3, -2e-3)),
        # Equidistant fisheye without coefficients: still not a pinhole.
        Camera("OPENCV_FISHEYE", W, H, (300.0, 300.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0)),
        Camera("OPENCV_FISHEYE", W, H, (300.0, 301.0, 321.5, 238.25, -0.00228, 0.0373, -0.0351, 0.00552)),
    ],
    ids=lambda c: f"{c.model.value}{'' if c.has_distortion else '-undistorted'}",
)
def test_rays_are_the_cameras_undistorted_rays(camera: Camera) -> None:
    px = np.random.default_rng(0).uniform([0, 0], [W, H], (200, 2))
    rays = _rays(camera, px)
    assert rays.shape == (200, 3)
    np.testing.assert_allclose(rays, camera.bearings_from_img(px), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(camera.img_from_cam(rays), px, atol=1e-6)
