"""A camera's mount pitch and roll: the rotation that makes it upright, and the angles of a gravity."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.validation import InputError
from planarloc.gravity.upright import pitch_roll_from_gravity, upright_from_cam_rotation


@pytest.mark.parametrize(("pitch", "roll"), [(0.0, 0.0), (12.0, -4.0), (-8.0, 3.5), (25.0, 10.0)])
def test_the_rotation_makes_the_camera_upright(pitch, roll):
    """Points of the upright frame (y = gravity) seen by the mounted camera come back upright,
    a vertical line stays vertical, and the rotation is a rotation."""
    R_upright_from_cam = upright_from_cam_rotation(pitch, roll)
    assert (
        np.allclose(R_upright_from_cam @ R_upright_from_cam.T, np.eye(3))
        and np.linalg.det(R_upright_from_cam) > 0
    )
    X_up = np.column_stack([np.full(10, 0.7), np.linspace(-1, 1.5, 10), np.full(10, 6.0)])  # a vertical line
    X_cam = X_up @ R_upright_from_cam  # R_cam_from_upright applied row-wise
    back = X_cam @ R_upright_from_cam.T
    assert np.allclose(back, X_up, atol=1e-12) and np.ptp(back[:, 0]) < 1e-12


def test_angle_signs():
    # Looking down: the horizon (horizontal directions at infinity) appears above the principal point.
    R = upright_from_cam_rotation(10.0, 0.0)
    horizon_cam = R.T @ np.array([0.0, 0.0, 1.0])
    assert horizon_cam[1] < 0
    # Right side lower (roll > 0): the camera x-axis has a downward component.
    assert upright_from_cam_rotation(0.0, 5.0)[1, 0] > 0
    # Looking down 10°: the optical axis has a downward component sin(10°) in the upright frame.
    assert (R @ [0.0, 0.0, 1.0])[1] == pytest.approx(np.sin(np.radians(10.0)))


def test_pitch_roll_from_gravity_inverts_the_rotation():
    for pitch, roll in [(0.0, 0.0), (12.0, -4.0), (-30.0, 170.0), (60.0, 45.0)]:
        g_cam = upright_from_cam_rotation(pitch, roll).T @ np.array([0.0, 1.0, 0.0])
        p, r = pitch_roll_from_gravity(3.0 * g_cam)
        assert (p, r) == pytest.approx((pitch, roll), abs=1e-9)
    with pytest.raises(InputError, match="zero"):
        pitch_roll_from_gravity([0.0, 0.0, 0.0])


def test_bad_inputs():
    with pytest.raises(InputError):
        upright_from_cam_rotation(float("nan"), 0.0)
    with pytest.raises(InputError):
        pitch_roll_from_gravity([0.0, 1.0])
