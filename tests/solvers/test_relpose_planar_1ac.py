"""Planar relative pose from one affine correspondence (Guan et al. CVPR 2020, Sec. 3.1):
ground truth, the affine–essential relation, degeneracies, batch/single agreement."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.epipolar import essential_from_relpose
from planarloc.geometry.planar import is_planar, relpose_from_planar_params
from planarloc.geometry.validation import InputError
from planarloc.solvers.relpose_planar_1ac import relpose_planar_1ac, relpose_planar_1ac_batch

EXACT = 1e-8


def affine_correspondence(pose, X: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays ``(x, y, 1)`` xq, xr of the point X (query frame) and the true affine map A (2, 2): the
    Jacobian at X of the homography ``H = R + t nᵀ / d`` of its surface patch (unit normal n)."""
    H = pose.R + np.outer(pose.t, n) / (n @ X)
    xq = X / X[2]
    y = H @ xq
    xr = y / y[2]
    A = (H[:2, :2] - np.outer(xr[:2], H[2, :2])) / y[2]
    return xq, xr, A


def affine_scenes(rng: np.random.Generator, m: int, min_depth: float = 0.1):
    """m random planar scenes with one affine correspondence each (the paper's protocol, Sec. V-A).

    Yaw θ and direction φ uniform in [-π, π], unit baseline; a point uniform in [-10, 10]³ (query
    frame) in front of both cameras, on a surface patch with a random normal. The true affine
    map is the Jacobian of the patch's homography ``H = R + t nᵀ / d`` at the point.

    Returns:
        theta, phi (M,), R (M, 3, 3), t (M, 3), xq, xr (M, 3) rays ``(x, y, 1)``, A (M, 2, 2).
    """
    out = []
    while len(out) < m:
        theta, phi = rng.uniform(-np.pi, np.pi, 2)
        pose = relpose_from_planar_params(theta, phi)
        X = rng.uniform(-10.0, 10.0, 3)
        if X[2] < min_depth or (pose.R @ X + pose.t)[2] < min_depth:
            continue
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        xq, xr, A = affine_correspondence(pose, X, n)
        out.append((theta, phi, pose.R, pose.t, xq, xr, A))
    return [np.array(v) for v in zip(*out)]


def test_true_affine_satisfies_the_affine_essential_relation() -> None:
    """(Eᵀ x_r)_{1:2} + Aᵀ (E x_q)_{1:2} = 0 and x_rᵀ E x_q = 0 for the scene generator."""
    _, _, R, t, xq, xr, A = affine_scenes(np.random.default_rng(5), 50)
    for k in range(50):
        E = essential_from_relpose(R[k], t[k])
        assert abs(xr[k] @ E @ xq[k]) < 1e-12
        np.testing.assert_allclose((E.T @ xr[k])[:2] + A[k].T @ (E @ xq[k])[:2], 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_random_scenes_exactly(seed: int) -> None:
    theta, _phi, R, t, xq, xr, A = affine_scenes(np.random.default_rng(seed), 300)
    for k in range(len(theta)):
        poses = relpose_planar_1ac(xq[k], xr[k], A[k])
        assert len(poses) == 1
        assert is_planar(poses[0])
        assert np.linalg.norm(poses[0].R - R[k]) < EXACT
        assert np.linalg.norm(poses[0].t - t[k]) < EXACT


def test_batch_matches_single_calls_and_reports_zero_imbalance() -> None:
    _theta, _phi, R, t, xq, xr, A = affine_scenes(np.random.default_rng(3), 200)
    Rb, tb, valid, imb = relpose_planar_1ac_batch(xq, xr, A)
    assert Rb.shape == (200, 1, 3, 3) and tb.shape == (200, 1, 3) and valid.shape == imb.shape == (200, 1)
    assert valid.all()
    np.testing.assert_allclose(Rb[:, 0], R, atol=EXACT)
    np.testing.assert_allclose(tb[:, 0], t, atol=EXACT)
    assert np.abs(imb).max() < 1e-9
    for k in range(0, 200, 17):
        pose = relpose_planar_1ac(xq[k], xr[k], A[k])[0]
        np.testing.assert_allclose(pose.R, Rb[k, 0], atol=1e-12)
        np.testing.assert_allclose(pose.t, tb[k, 0], atol=1e-12)


def test_parallel_batch_path_agrees() -> None:
    _theta, _phi, _R, t, xq, xr, A = affine_scenes(np.random.default_rng(4), 300)
    reps = 5000 // 300 + 1  # above the parallel threshold
    _Rb, tb, valid, _ = relpose_planar_1ac_batch(
        np.tile(xq, (reps, 1)), np.tile(xr, (reps, 1)), np.tile(A, (reps, 1, 1))
    )
    assert valid.all()
    np.testing.assert_allclose(tb[:, 0], np.tile(t, (reps, 1)), atol=EXACT)


def test_bearings_and_2d_points_are_accepted() -> None:
    _theta, _phi, _R, t, xq, xr, A = affine_scenes(np.random.default_rng(6), 5)
    for k in range(5):
        bq, br = xq[k] / np.linalg.norm(xq[k]), 3.0 * xr[k] / np.linalg.norm(xr[k])
        assert np.linalg.norm(relpose_planar_1ac(bq, br, A[k])[0].t - t[k]) < EXACT
        assert np.linalg.norm(relpose_planar_1ac(xq[k][:2], list(xr[k][:2]), A[k])[0].t - t[k]) < EXACT


# ---- degenerate configurations --------------------------------------------------------------


def rotation_only_correspondence(rng: np.random.Generator, theta: float):
    """A point seen under a pure rotation (zero baseline, or equally a point at infinity): x_r ∝ R x_q
    and A is the Jacobian of the infinite homography R."""
    pose = relpose_from_planar_params(theta, 0.0, 0.0)
    while True:
        xq = np.array([*rng.uniform(-0.6, 0.6, 2), 1.0])
        y = pose.R @ xq
        if y[2] > 0.2:
            break
    xr = y / y[2]
    A = (pose.R[:2, :2] - np.outer(xr[:2], pose.R[2, :2])) / y[2]
    return xq, xr, A


@pytest.mark.parametrize("theta", [0.0, 0.3, -1.0])
def test_zero_translation_and_point_at_infinity_give_no_solution(theta: float) -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        xq, xr, A = rotation_only_correspondence(rng, theta)
        assert relpose_planar_1ac(xq, xr, A) == []
        _, _, valid, imb = relpose_planar_1ac_batch(xq[None], xr[None], A[None])
        assert not valid.any() and np.isnan(imb).all()


def test_very_distant_point_with_a_baseline_gives_no_solution() -> None:
    """A point 1e9 baselines away: parallel rays, no depth, no pose (not a random one)."""
    pose = relpose_from_planar_params(0.4, 1.1)
    X = 1e9 * np.array([0.3, -0.1, 1.0])
    n = np.array([0.0, 0.0, 1.0])
    xq, xr, A = affine_correspondence(pose, X, n)
    assert relpose_planar_1ac(xq, xr, A) == []


def test_point_on_the_horizon_of_both_views_gives_no_solution() -> None:
    """y = 0 in both views (a point at the cameras' height): the epipolar row vanishes."""
    pose = relpose_from_planar_params(0.3, 0.8)
    X = np.array([1.0, 0.0, 6.0])
    n = np.array([0.2, 0.5, -1.0])
    n /= np.linalg.norm(n)
    xq, xr, A = affine_correspondence(pose, X, n)
    assert abs(xr[1]) < 1e-15
    assert relpose_planar_1ac(xq, xr, A) == []


def test_inconsistent_affine_frame_is_flagged_not_silently_accepted() -> None:
    """An affine map no planar motion produces gives a large |imbalance| (or no solution); the
    true frame gives 0. ``max_imbalance`` turns the flag into a rejection."""
    _theta, _phi, _R, _t, xq, xr, A = affine_scenes(np.random.default_rng(8), 200)
    rng = np.random.default_rng(9)
    bad = A + rng.normal(scale=1.0, size=A.shape) * np.linalg.norm(A, axis=(1, 2))[:, None, None]
    _, _, valid_true, imb_true = relpose_planar_1ac_batch(xq, xr, A)
    _, tb, valid_bad, imb_bad = relpose_planar_1ac_batch(xq, xr, bad)
    assert valid_true.all() and np.abs(imb_true).max() < 1e-9
    flagged = ~valid_bad[:, 0] | (np.abs(imb_bad[:, 0]) > 0.05)
    assert flagged.mean() > 0.8
    # the ones not flagged are rare and are not garbage-by-construction: the output is a valid pose
    ok = valid_bad[:, 0]
    np.testing.assert_allclose(np.linalg.norm(tb[ok, 0], axis=1), 1.0)
    k = int(np.argmax(np.abs(np.nan_to_num(imb_bad[:, 0]))))
    assert len(relpose_planar_1ac(xq[k], xr[k], bad[k])) == 1
    assert relpose_planar_1ac(xq[k], xr[k], bad[k], max_imbalance=0.05) == []


def test_a_frame_with_a_vanishing_circle_pair_gives_no_solution() -> None:
    """A = 0 and a point on the vertical centre line: the null vector has x3 = x4 = 0."""
    xq = np.array([0.0, 0.3, 1.0])
    xr = np.array([0.0, 0.2, 1.0])
    assert relpose_planar_1ac(xq, xr, np.zeros((2, 2))) == []


def test_point_behind_the_cameras_for_both_signs_gives_no_solution() -> None:
    """A correspondence whose point is in front of one camera and behind the other for either sign
    of t (the reference ray mirrored) is rejected by cheirality."""
    _theta, _phi, _R, _t, xq, xr, A = affine_scenes(np.random.default_rng(10), 100)
    rejected = 0
    for k in range(100):
        xr_m = xr[k].copy()
        xr_m[:2] *= -1  # mirror through the principal point (a wrong match)
        A_m = -A[k]
        poses = relpose_planar_1ac(xq[k], xr_m, A_m)
        for p in poses:  # whatever is returned must satisfy cheirality of its own point
            a, b = p.R @ xq[k], xr_m
            M = np.stack([a, -b], 1)
            lam = np.linalg.lstsq(M, -p.t, rcond=None)[0]
            assert (lam > 0).all()
        rejected += not poses
    assert rejected > 0


def test_invalid_input_raises() -> None:
    with pytest.raises(InputError):
        relpose_planar_1ac(np.zeros(4), np.zeros(3), np.eye(2))
    with pytest.raises(InputError):
        relpose_planar_1ac(np.array([0.0, np.nan, 1.0]), np.array([0.0, 0.1, 1.0]), np.eye(2))
    with pytest.raises(InputError):
        relpose_planar_1ac(np.array([0.0, 0.1, 1.0]), np.array([0.0, 0.1, 1.0]), np.eye(3))
    with pytest.raises(InputError):
        relpose_planar_1ac_batch(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 2, 2)))
    with pytest.raises(InputError):
        relpose_planar_1ac(np.array([0.0, 0.1, 1.0]), np.array([0.0, 0.1, 1.0]), np.eye(2), max_imbalance=-1)
