"""Gravity-levelling rotations (planarloc.geometry.gravity)."""

import numpy as np
import pytest

from planarloc.geometry.gravity import mean_direction, tilt_between_deg, upright_from_gravity


def test_levels_any_direction_with_a_proper_rotation() -> None:
    rng = np.random.default_rng(0)
    g = rng.normal(size=(200, 3)) * rng.uniform(0.1, 10.0, (200, 1))
    U = upright_from_gravity(g)
    gn = g / np.linalg.norm(g, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", U, gn), np.tile([0.0, 1.0, 0.0], (200, 1)), atol=1e-12)
    np.testing.assert_allclose(U @ np.swapaxes(U, 1, 2), np.broadcast_to(np.eye(3), U.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=1e-12)


def test_smallest_rotation_keeps_the_heading() -> None:
    # A camera pitched down by 10° is levelled by a rotation about its x-axis only.
    a = np.radians(10.0)
    U = upright_from_gravity(np.array([0.0, np.cos(a), np.sin(a)]))
    np.testing.assert_allclose(U[0], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arccos(U[2, 2])), 10.0, atol=1e-9)
    np.testing.assert_allclose(upright_from_gravity(np.array([0.0, 2.0, 0.0])), np.eye(3), atol=1e-15)


def test_upside_down_is_a_half_turn() -> None:
    U = upright_from_gravity(np.array([0.0, -1.0, 0.0]))
    np.testing.assert_allclose(U @ [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    assert np.linalg.det(U) == pytest.approx(1.0)


def test_tilt_and_mean() -> None:
    assert tilt_between_deg([0, 1, 0], [0, 1, 1]) == pytest.approx(45.0)
    m = mean_direction(np.array([[0.0, 1.0, 0.1], [0.0, 1.0, -0.1]]))
    np.testing.assert_allclose(m, [0.0, 1.0, 0.0], atol=1e-12)
