"""The local planar motion model, paper Sec. III-A, eq. (1)-(2)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from planarloc.geometry.epipolar import essential_from_relpose
from planarloc.geometry.planar import (
    essential_from_planar_params,
    is_planar,
    planar_params_from_relpose,
    relpose_from_planar_params,
    rotation_from_yaw,
    upright_tilt_deg,
    yaw_from_rotation,
)
from planarloc.geometry.pose import Pose
from planarloc.synthetic.scenes import random_planar_pose

angles = st.floats(-np.pi, np.pi, allow_nan=False)
scales = st.floats(1e-3, 1e3, allow_nan=False)


def wrap(a: float) -> float:
    """Angle in (-π, π]."""
    return float(np.arctan2(np.sin(a), np.cos(a)))


# ---- eq. (1) ----------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(angles)
def test_rotation_from_yaw_is_eq1(theta: float) -> None:
    c, s = np.cos(theta), np.sin(theta)
    R = rotation_from_yaw(theta)
    np.testing.assert_array_equal(R, [[c, 0, -s], [0, 1, 0], [s, 0, c]])
    # eq. (1) is the right-handed rotation by -θ about +y (Rotation.from_rotvec([0, -θ, 0])).
    np.testing.assert_allclose(R, Rotation.from_rotvec([0.0, -theta, 0.0]).as_matrix(), atol=1e-15)
    assert yaw_from_rotation(R) == pytest.approx(wrap(theta), abs=1e-12) or abs(abs(theta) - np.pi) < 1e-12


def test_rotation_from_yaw_broadcasts() -> None:
    th = np.linspace(-3, 3, 12).reshape(3, 4)
    R = rotation_from_yaw(th)
    assert R.shape == (3, 4, 3, 3)
    np.testing.assert_array_equal(R[1, 2], rotation_from_yaw(th[1, 2]))


@settings(max_examples=50, deadline=None)
@given(angles, angles, scales)
def test_relpose_from_planar_params_is_eq1(theta: float, phi: float, rho: float) -> None:
    ref_from_query = relpose_from_planar_params(theta, phi, rho)
    R = rotation_from_yaw(theta)
    np.testing.assert_allclose(ref_from_query.R, R, atol=1e-15)
    direction = np.array([np.sin(phi), 0.0, np.cos(phi)])
    np.testing.assert_allclose(ref_from_query.t, -R @ (rho * direction), atol=1e-12 * rho)
    # ρ (sin φ, 0, cos φ) is the reference camera centre in query coordinates.
    np.testing.assert_allclose(ref_from_query.center, rho * direction, atol=1e-12 * rho)
    np.testing.assert_allclose(ref_from_query.inverse().t, rho * direction, atol=1e-12 * rho)
    assert is_planar(ref_from_query)


# ---- eq. (2) ----------------------------------------------------------------------------------


@settings(max_examples=50, deadline=None)
@given(angles, angles, scales)
def test_essential_from_planar_params_is_t_cross_R(theta: float, phi: float, rho: float) -> None:
    E = essential_from_planar_params(theta, phi, rho)
    pose = relpose_from_planar_params(theta, phi, rho)
    np.testing.assert_allclose(E, essential_from_relpose(pose.R, pose.t), atol=1e-12 * rho)
    expected = rho * np.array(
        [[0, np.cos(theta - phi), 0], [-np.cos(phi), 0, np.sin(phi)], [0, np.sin(theta - phi), 0]]
    )
    np.testing.assert_allclose(E, expected, atol=1e-15 * rho)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planar_essential_satisfies_the_epipolar_constraint(seed: int) -> None:
    """``x_refᵀ E x_query = 0`` for points seen by both cameras (not ``x_queryᵀ E x_ref``)."""
    rng = np.random.default_rng(seed)
    theta, phi, rho = rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi), rng.uniform(0.1, 5.0)
    ref_from_query = relpose_from_planar_params(theta, phi, rho)
    X_q = rng.uniform(-10, 10, (200, 3))
    X_r = ref_from_query.transform(X_q)
    E = essential_from_planar_params(theta, phi, rho)
    norms = np.linalg.norm(X_r, axis=1) * np.linalg.norm(X_q, axis=1)
    r = np.einsum("ij,jk,ik->i", X_r, E, X_q) / norms
    np.testing.assert_allclose(r, 0.0, atol=1e-13 * rho)
    r_swapped = np.einsum("ij,jk,ik->i", X_q, E, X_r) / norms
    assert np.abs(r_swapped).max() > 1e-3


# ---- conversions ------------------------------------------------------------------------------


@settings(max_examples=50, deadline=None)
@given(angles, angles, scales)
def test_planar_params_round_trip(theta: float, phi: float, rho: float) -> None:
    th, ph, rh = planar_params_from_relpose(relpose_from_planar_params(theta, phi, rho))
    assert -np.pi <= th <= np.pi and -np.pi <= ph <= np.pi
    assert wrap(th - theta) == pytest.approx(0.0, abs=1e-9)
    assert wrap(ph - phi) == pytest.approx(0.0, abs=1e-9)
    assert rh == pytest.approx(rho, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_relative_pose_of_two_upright_cameras_is_planar_and_round_trips(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(50):
        query, ref = random_planar_pose(rng), random_planar_pose(rng)
        ref_from_query = ref @ query.inverse()
        assert is_planar(ref_from_query)
        theta, phi, rho = planar_params_from_relpose(ref_from_query)
        back = relpose_from_planar_params(theta, phi, rho)
        np.testing.assert_allclose(back.R, ref_from_query.R, atol=1e-12)
        np.testing.assert_allclose(back.t, ref_from_query.t, atol=1e-12)
        assert rho == pytest.approx(np.linalg.norm(ref.center - query.center), rel=1e-12)


def test_zero_translation_gives_rho_zero() -> None:
    rotation_only = Pose(rotation_from_yaw(0.4), np.zeros(3))
    assert planar_params_from_relpose(rotation_only) == pytest.approx((0.4, 0.0, 0.0))


@pytest.mark.parametrize(
    "pose",
    [
        Pose(Rotation.from_rotvec([1e-3, 0.0, 0.0]).as_matrix(), [0.0, 0.0, 1.0]),  # pitch
        Pose(Rotation.from_rotvec([0.0, 0.3, 1e-3]).as_matrix(), [1.0, 0.0, 1.0]),  # yaw + roll
        Pose(np.eye(3), [1.0, 1e-3, 0.0]),  # vertical translation
    ],
    ids=["pitch", "roll", "t_y"],
)
def test_non_planar_pose_is_rejected(pose: Pose) -> None:
    assert not is_planar(pose)
    with pytest.raises(ValueError, match="not a planar motion"):
        planar_params_from_relpose(pose)


def test_is_planar_tolerance() -> None:
    tiny = Pose(Rotation.from_rotvec([1e-9, 0.5, 0.0]).as_matrix(), [3.0, 1e-9, -2.0])
    assert is_planar(tiny)
    assert not is_planar(tiny, tol=1e-12)
    # The translation tolerance is relative to ‖t‖ when ‖t‖ > 1.
    assert is_planar(Pose(np.eye(3), [1000.0, 1e-4, 0.0]))
    assert not is_planar(Pose(np.eye(3), [1.0, 1e-4, 0.0]))


def test_upright_tilt() -> None:
    rng = np.random.default_rng(0)
    upright = random_planar_pose(rng)
    assert upright_tilt_deg(upright) == pytest.approx(0.0, abs=1e-6)
    pitched = Pose(Rotation.from_rotvec([np.radians(5.0), 0.0, 0.0]).as_matrix() @ upright.R, upright.t)
    assert upright_tilt_deg(pitched) == pytest.approx(5.0, abs=1e-9)
    assert upright_tilt_deg(upright, gravity_world=(0.0, -2.0, 0.0)) == pytest.approx(180.0, abs=1e-6)
