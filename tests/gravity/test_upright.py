"""Upright rectification of a camera with known mounting pitch and roll."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.gravity.upright import (
    apply_homography,
    pitch_roll_from_gravity,
    rectified_camera,
    rectify_homography,
    rectify_keypoints,
    unrectify_keypoints,
    upright_bearings,
    upright_from_cam_rotation,
)

PINHOLE = Camera("PINHOLE", 640, 480, (520.0, 515.0, 322.0, 241.0))
OPENCV = Camera("OPENCV", 640, 480, (520.0, 515.0, 322.0, 241.0, -0.12, 0.02, 0.001, -0.0005))


def pixels(n: int = 200, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 2)) * [640.0, 480.0]


@pytest.mark.parametrize("camera", [PINHOLE, OPENCV])
@pytest.mark.parametrize(("pitch", "roll"), [(0.0, 0.0), (12.0, -4.0), (-8.0, 3.5), (25.0, 10.0)])
def test_round_trip(camera, pitch, roll):
    pts = pixels()
    rect, ok = rectify_keypoints(camera, pts, pitch, roll)
    back, ok_back = unrectify_keypoints(camera, rect, pitch, roll)
    assert ok.all() and ok_back.all()
    assert np.allclose(back, pts, atol=1e-6)


def test_homography_equals_keypoint_mapping_for_pinhole():
    pts = pixels()
    H = rectify_homography(PINHOLE, 12.0, -4.0)
    via_h, ok = apply_homography(H, pts)
    direct, _ = rectify_keypoints(PINHOLE, pts, 12.0, -4.0)
    assert ok.all() and np.allclose(via_h, direct, atol=1e-8)
    back, _ = apply_homography(np.linalg.inv(H), via_h)
    assert np.allclose(back, pts, atol=1e-8)
    assert np.allclose(rectify_homography(PINHOLE, 0.0, 0.0), np.eye(3))


@pytest.mark.parametrize("camera", [PINHOLE, OPENCV])
def test_rectified_points_are_seen_by_the_upright_camera(camera):
    """Project 3D points (upright frame, y = gravity) into the tilted camera, rectify, and compare
    with their projection by the virtual upright camera; vertical lines become vertical."""
    pitch, roll = 15.0, -6.0
    R_upright_from_cam = upright_from_cam_rotation(pitch, roll)
    rng = np.random.default_rng(3)
    X_up = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-1, 1.5, 50), rng.uniform(4, 10, 50)])
    X_up[25:, 0] = 0.7  # a vertical line x = 0.7, z = 6
    X_up[25:, 2] = 6.0
    X_cam = X_up @ R_upright_from_cam  # R_cam_from_upright applied row-wise
    observed = camera.img_from_cam(X_cam)
    rect, ok = rectify_keypoints(camera, observed, pitch, roll)
    expected = rectified_camera(camera).img_from_cam(X_up)
    assert ok.all() and np.allclose(rect, expected, atol=1e-6)
    assert np.ptp(rect[25:, 0]) < 1e-6  # the vertical line is vertical after rectification
    assert np.ptp(observed[25:, 0]) > 1.0  # ... and was not before


def test_angle_signs():
    # Looking down: the horizon (horizontal directions at infinity) appears above the principal point.
    R = upright_from_cam_rotation(10.0, 0.0)
    horizon_cam = R.T @ np.array([0.0, 0.0, 1.0])
    assert horizon_cam[1] < 0
    # Right side lower (roll > 0): the camera x-axis has a downward component.
    assert upright_from_cam_rotation(0.0, 5.0)[1, 0] > 0
    bearings = upright_bearings(PINHOLE, np.array([[322.0, 241.0]]), 10.0, 0.0)
    assert bearings[0, 1] > 0 and np.linalg.norm(bearings[0]) == pytest.approx(1.0)


def test_pitch_roll_from_gravity_inverts_the_rotation():
    for pitch, roll in [(0.0, 0.0), (12.0, -4.0), (-30.0, 170.0), (60.0, 45.0)]:
        g_cam = upright_from_cam_rotation(pitch, roll).T @ np.array([0.0, 1.0, 0.0])
        p, r = pitch_roll_from_gravity(3.0 * g_cam)
        assert (p, r) == pytest.approx((pitch, roll), abs=1e-9)
    with pytest.raises(InputError, match="zero"):
        pitch_roll_from_gravity([0.0, 0.0, 0.0])


def test_points_behind_the_virtual_camera_are_flagged():
    # Looking up 80° with a wide camera: the top row looks another 67° up, i.e. behind the upright view.
    wide = Camera("PINHOLE", 640, 480, (100.0, 100.0, 320.0, 240.0))
    pts = np.array([[320.0, 240.0], [320.0, 0.0]])
    _, ok = rectify_keypoints(wide, pts, -80.0, 0.0)
    assert ok.tolist() == [True, False]


def test_bad_inputs():
    with pytest.raises(InputError):
        upright_from_cam_rotation(float("nan"), 0.0)
    with pytest.raises(InputError, match="Camera"):
        rectify_homography("PINHOLE", 1.0, 2.0)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"\(N, 2\)"):
        rectify_keypoints(PINHOLE, np.zeros((3, 3)), 1.0, 2.0)
