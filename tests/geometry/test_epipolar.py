"""Two-view epipolar math: ``x_refᵀ E x_query = 0``, Sampson error in pixels, triangulation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import (
    essential_from_relpose,
    sampson_error_sq,
    skew,
    triangulate_points,
    triangulation_depths,
)
from planarloc.geometry.pose import Pose

CAM_Q = Camera("PINHOLE", 1280, 1080, (800.0, 780.0, 640.0, 540.0))
CAM_R = Camera("PINHOLE", 640, 480, (520.0, 530.0, 320.0, 240.0))


def random_two_view(rng: np.random.Generator, n: int = 200) -> tuple[Pose, np.ndarray, np.ndarray]:
    """A general (6-DoF) ``ref_from_query``, and (n, 3) points in front of both cameras (query frame)."""
    ref_from_query = Pose(Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), rng.normal(0, 1, 3))
    X = np.c_[rng.uniform(-4, 4, (4 * n, 2)), rng.uniform(3, 20, 4 * n)]
    Xr = ref_from_query.transform(X)
    X = X[Xr[:, 2] > 0.5][:n]
    assert len(X) == n
    return ref_from_query, X, ref_from_query.transform(X)


def hom(x: np.ndarray) -> np.ndarray:
    return np.hstack([x, np.ones((len(x), 1))])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=6, max_size=6))
def test_skew_is_the_cross_product(v: list[float]) -> None:
    a, b = np.array(v[:3]), np.array(v[3:])
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b), atol=1e-12)
    np.testing.assert_array_equal(skew(a), -skew(a).T)
    batched = skew(np.stack([a, b])) @ b
    np.testing.assert_allclose(batched, np.stack([np.cross(a, b), np.zeros(3)]), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_essential_from_relpose_direction_convention(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref_from_query, X, Xr = random_two_view(rng)
    E = essential_from_relpose(ref_from_query.R, ref_from_query.t)
    xq, xr = X / X[:, 2:], Xr / Xr[:, 2:]
    np.testing.assert_allclose(np.einsum("ij,jk,ik->i", xr, E, xq), 0.0, atol=1e-12)
    Es = essential_from_relpose(np.stack([ref_from_query.R] * 2), np.stack([ref_from_query.t] * 2))
    assert Es.shape == (2, 3, 3)
    np.testing.assert_allclose(Es[1], E)


# ---- Sampson error ----------------------------------------------------------------------------


def _pixel_setup(seed: int, noise_px: float):
    rng = np.random.default_rng(seed)
    ref_from_query, X, Xr = random_two_view(rng)
    E = essential_from_relpose(ref_from_query.R, ref_from_query.t)
    uq = CAM_Q.img_from_cam(X) + rng.normal(0, noise_px, (len(X), 2))
    ur = CAM_R.img_from_cam(Xr) + rng.normal(0, noise_px, (len(X), 2))
    F = np.linalg.inv(CAM_R.K).T @ E @ np.linalg.inv(CAM_Q.K)
    xq, xr = CAM_Q.bearings_from_img(uq), CAM_R.bearings_from_img(ur)
    err = sampson_error_sq(E, xq, xr, CAM_Q.focal, CAM_R.focal)
    return E, F, uq, ur, xq, xr, err


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampson_error_is_zero_on_exact_matches(seed: int) -> None:
    *_, err = _pixel_setup(seed, 0.0)
    assert err.shape == (200,)
    assert np.sqrt(err.max()) < 1e-9  # pixels


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampson_combines_the_two_point_to_epipolar_line_distances(seed: int) -> None:
    """Two-sided identity: with d_ref the pixel distance of u_ref to the line F u_query and d_query
    the distance of u_query to Fᵀ u_ref, Sampson² = d_ref² d_query² / (d_ref² + d_query²)."""
    E, F, uq, ur, xq, xr, err = _pixel_setup(seed, 1.0)
    pq, pr = hom(uq), hom(ur)
    l_ref = pq @ F.T  # epipolar lines in the reference image
    l_query = pr @ F  # epipolar lines in the query image
    d_ref = np.abs(np.einsum("ij,ij->i", pr, l_ref)) / np.linalg.norm(l_ref[:, :2], axis=1)
    d_query = np.abs(np.einsum("ij,ij->i", pq, l_query)) / np.linalg.norm(l_query[:, :2], axis=1)
    np.testing.assert_allclose(err, d_ref**2 * d_query**2 / (d_ref**2 + d_query**2), rtol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampson_is_first_order_geometric_error_in_pixels(seed: int) -> None:
    """Against the optimal two-image correction (Hartley-Sturm, ``cv2.correctMatches``): the
    Sampson error approximates the squared pixel distance to the nearest exact match to first order."""
    E, F, uq, ur, xq, xr, err = _pixel_setup(seed, 0.5)
    cq, cr = cv2.correctMatches(F, uq[None], ur[None])
    gold = ((cq[0] - uq) ** 2).sum(1) + ((cr[0] - ur) ** 2).sum(1)
    np.testing.assert_allclose(err, gold, rtol=2e-3, atol=1e-12)
    # Normalized units: the same with unit focal lengths, and scaling with f² when fx = fy everywhere.
    err_norm = sampson_error_sq(E, xq, xr)
    f = 700.0
    np.testing.assert_allclose(sampson_error_sq(E, xq, xr, (f, f), (f, f)), f * f * err_norm, rtol=1e-12)


def test_sampson_error_is_invariant_to_the_scale_and_sign_of_E() -> None:
    E, F, uq, ur, xq, xr, err = _pixel_setup(0, 1.0)
    np.testing.assert_allclose(sampson_error_sq(-3.7 * E, xq, xr, CAM_Q.focal, CAM_R.focal), err, rtol=1e-9)


# ---- triangulation ----------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_triangulation_depths_are_the_true_depths(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref_from_query, X, Xr = random_two_view(rng)
    d = triangulation_depths(ref_from_query.R, ref_from_query.t, X / X[:, 2:], Xr / Xr[:, 2:])
    np.testing.assert_allclose(d, np.c_[X[:, 2], Xr[:, 2]], rtol=1e-9)
    # Bearing vectors: depths are distances.
    u, ur = X / np.linalg.norm(X, axis=1)[:, None], Xr / np.linalg.norm(Xr, axis=1)[:, None]
    d = triangulation_depths(ref_from_query.R, ref_from_query.t, u, ur)
    np.testing.assert_allclose(d, np.c_[np.linalg.norm(X, axis=1), np.linalg.norm(Xr, axis=1)], rtol=1e-9)
    # The wrong sign of t puts every point behind both cameras.
    d = triangulation_depths(ref_from_query.R, -ref_from_query.t, X / X[:, 2:], Xr / Xr[:, 2:])
    assert np.all(d < 0)


def test_triangulation_depths_are_nan_for_parallel_rays() -> None:
    rng = np.random.default_rng(0)
    ref_from_query, X, _ = random_two_view(rng, 20)
    xq = X / X[:, 2:]
    parallel = xq @ ref_from_query.R.T  # the same direction in the reference: a point at infinity
    d = triangulation_depths(ref_from_query.R, ref_from_query.t, xq, parallel)
    assert np.all(np.isnan(d))
    assert not np.any(d > 0)
    # Zero baseline with parallel rays (pure rotation) as well.
    assert np.all(np.isnan(triangulation_depths(ref_from_query.R, np.zeros(3), xq, parallel)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_triangulate_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a_from_world = Pose(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 2, 3))
    b_from_a, X_a, X_b = random_two_view(rng, 50)
    b_from_world = b_from_a @ a_from_world
    X_world = a_from_world.inverse().transform(X_a)
    xa, xb = X_a / X_a[:, 2:], X_b / X_b[:, 2:]
    Xw, angle = triangulate_points((a_from_world.R, a_from_world.t), (b_from_world.R, b_from_world.t), xa, xb)
    np.testing.assert_allclose(Xw, X_world, atol=1e-8 * np.abs(X_world).max())
    ca, cb = a_from_world.center, b_from_world.center
    da, db = X_world - ca, X_world - cb
    cos = np.einsum("ij,ij->i", da, db) / np.linalg.norm(da, axis=1) / np.linalg.norm(db, axis=1)
    expected = np.degrees(np.arccos(cos))
    np.testing.assert_allclose(angle, expected, atol=1e-6)
    # Rays that meet behind the cameras (wrong sign of the baseline) give NaN, not a point.
    flipped = Pose(b_from_a.R, -b_from_a.t) @ a_from_world
    Xw, _ = triangulate_points((a_from_world.R, a_from_world.t), (flipped.R, flipped.t), xa, xb)
    assert np.all(np.isnan(Xw))
    # Parallel rays (a point at infinity) give NaN.
    Xw, _ = triangulate_points(
        (a_from_world.R, a_from_world.t), (b_from_world.R, b_from_world.t), xa[:5], xa[:5] @ b_from_a.R.T
    )
    assert np.all(np.isnan(Xw))
