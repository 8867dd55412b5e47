"""Planar 2-point relative pose (paper Sec. IV-A): ground truth, degeneracies, peer libraries."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.epipolar import triangulation_depths
from planarloc.geometry.planar import is_planar, relpose_from_planar_params, rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.solvers.relpose_planar_2p import relpose_planar_2p, relpose_planar_2p_batch

SEEDS = [0, 1, 2]
EXACT = 1e-8


def planar_scenes(rng: np.random.Generator, m: int, n_points: int = 2, min_depth: float = 1e-3):
    """m random planar two-view scenes, the paper's protocol (Sec. V-A).

    Relative pose ``ref_from_query`` with yaw θ and direction φ uniform in [-π, π] and unit
    baseline; points uniform in [-10, 10]³ (query frame) kept if in front of both cameras
    (depth > ``min_depth``). Scenes without ``n_points`` such points are dropped.

    Returns:
        theta (M,), phi (M,), R (M, 3, 3), t (M, 3), xq (M, n, 3), xr (M, n, 3) with rays
        ``(x, y, 1)``, and the points X (M, n, 3) in the query frame.
    """
    theta, phi = rng.uniform(-np.pi, np.pi, (2, m))
    R = rotation_from_yaw(theta)
    t = -np.einsum("mij,mj->mi", R, np.stack([np.sin(phi), np.zeros(m), np.cos(phi)], axis=1))
    X = rng.uniform(-10.0, 10.0, (m, 16 * n_points, 3))
    Xr = np.einsum("mij,mkj->mki", R, X) + t[:, None]
    ok = (X[..., 2] > min_depth) & (Xr[..., 2] > min_depth)
    keep = ok.sum(axis=1) >= n_points
    order = np.argsort(~ok, axis=1, kind="stable")[:, :n_points, None]
    X, Xr = np.take_along_axis(X, order, 1)[keep], np.take_along_axis(Xr, order, 1)[keep]
    return theta[keep], phi[keep], R[keep], t[keep], X / X[..., 2:], Xr / Xr[..., 2:], X


def pose_error(a: Pose, R: np.ndarray, t: np.ndarray) -> float:
    """max(‖R_a - R‖_F, ‖t_a/‖t_a‖ - t/‖t‖‖)."""
    return max(
        float(np.linalg.norm(a.R - R)),
        float(np.linalg.norm(a.t / np.linalg.norm(a.t) - t / np.linalg.norm(t))),
    )


# ---- ground truth -----------------------------------------------------------------------------


def midpoint_depths(R: np.ndarray, t: np.ndarray, xq: np.ndarray, xr: np.ndarray) -> np.ndarray:
    """Depths (..., n, 2) with λ_r x_r ≈ λ_q R x_q + t, independent of the library (least squares)."""
    a = np.einsum("...ij,...nj->...ni", R, xq)  # query rays in the reference frame
    b = np.broadcast_to(xr, a.shape)
    tt = np.broadcast_to(t[..., None, :], a.shape)
    # Normal equations of min |λ_q a + t - λ_r b|², solved by Cramer's rule.
    aa, bb, ab = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
    at, bt = (a * tt).sum(-1), (b * tt).sum(-1)
    det = aa * bb - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([(ab * bt - bb * at) / det, (aa * bt - ab * at) / det], axis=-1)


@pytest.mark.parametrize("seed", SEEDS)
def test_noise_free_exact_recovery_on_random_planar_scenes(seed: int) -> None:
    """Thousands of scenes through the batch API: the truth is always among the solutions
    (< 1e-8), and every returned solution passes cheirality and the epipolar constraint."""
    rng = np.random.default_rng(seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 12000)
    assert len(theta) > 10000
    Rs, ts, valid = relpose_planar_2p_batch(xq, xr)
    # A sample is declared degenerate (no solution) when a candidate has exactly parallel rays
    # for one match (a point at infinity for that candidate: cheirality cannot decide); that is
    # a measure-zero coincidence for random scenes.
    assert (~valid[:, 0]).mean() < 1e-3
    assert np.isnan(Rs[~valid]).all() and np.isnan(ts[~valid]).all()
    err = np.maximum(np.linalg.norm(Rs - R[:, None], axis=(2, 3)), np.linalg.norm(ts - t[:, None], axis=2))
    assert np.where(valid, err, np.inf).min(axis=1)[valid[:, 0]].max() < EXACT
    depths = midpoint_depths(Rs, ts, xq[:, None], xr[:, None])  # (M, 2 solutions, 2 points, 2)
    assert np.all(depths[valid] > 0)
    E = np.cross(ts[..., None, :], np.swapaxes(Rs, -1, -2)).swapaxes(-1, -2)  # [t]x R
    res = np.einsum("mpi,mkij,mpj->mkp", xr, E, xq)
    assert np.abs(res[valid]).max() < 1e-10 * np.abs(xr).max() * np.abs(xq).max()


@pytest.mark.parametrize("seed", SEEDS)
def test_single_call_exact_recovery_and_cheirality(seed: int) -> None:
    rng = np.random.default_rng(50 + seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 400)
    for i in range(len(theta)):
        sols = relpose_planar_2p(xq[i], xr[i])
        assert 1 <= len(sols) <= 2
        assert min(pose_error(p, R[i], t[i]) for p in sols) < EXACT
        for p in sols:
            assert is_planar(p, tol=1e-12)
            assert np.linalg.norm(p.t) == pytest.approx(1.0, abs=1e-12)
            assert np.all(triangulation_depths(p.R, p.t, xq[i], xr[i]) > 0)


@pytest.mark.parametrize("seed", SEEDS)
def test_batch_agrees_with_single(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 1000)
    Rs, ts, valid = relpose_planar_2p_batch(xq, xr)
    assert (
        valid.shape == (len(theta), 2)
        and Rs.shape == (len(theta), 2, 3, 3)
        and ts.shape == (len(theta), 2, 3)
    )
    assert not np.any(valid[:, 1] & ~valid[:, 0])  # valid solutions are packed first
    # Identical to the single-call API on a subset.
    for i in rng.choice(len(theta), 300, replace=False):
        single = relpose_planar_2p(xq[i], xr[i])
        assert len(single) == valid[i].sum()
        for k, p in enumerate(single):
            np.testing.assert_allclose(p.R, Rs[i, k], atol=1e-14)
            np.testing.assert_allclose(p.t, ts[i, k], atol=1e-14)


def test_accepts_2d_normalized_points_and_bearings() -> None:
    rng = np.random.default_rng(7)
    _, _, R, t, xq, xr, X = planar_scenes(rng, 10)
    ref = relpose_planar_2p(xq[0], xr[0])
    from_2d = relpose_planar_2p(xq[0, :, :2], xr[0, :, :2])
    unit = relpose_planar_2p(xq[0] / np.linalg.norm(xq[0], axis=1)[:, None], 3.0 * xr[0])
    assert len(ref) == len(from_2d) == len(unit)
    for a, b, c in zip(ref, from_2d, unit):
        np.testing.assert_allclose(a.R, b.R, atol=1e-14)
        np.testing.assert_allclose(a.R, c.R, atol=1e-12)
        np.testing.assert_allclose(a.t, c.t, atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_small_noise_gives_near_exact_poses(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 3000, min_depth=1.0)
    sigma = 1e-6  # normalized units: ~1e-3 px at f = 800
    xq_n = xq.copy()
    xr_n = xr.copy()
    xq_n[..., :2] += rng.normal(0, sigma, xq[..., :2].shape)
    xr_n[..., :2] += rng.normal(0, sigma, xr[..., :2].shape)
    Rs, ts, valid = relpose_planar_2p_batch(xq_n, xr_n)
    err = np.maximum(np.linalg.norm(Rs - R[:, None], axis=(2, 3)), np.linalg.norm(ts - t[:, None], axis=2))
    best = np.where(valid, err, np.inf).min(axis=1)
    # Two-point samples can be ill-conditioned (e.g. both points near the horizon row), so the
    # error is checked statistically; a noisy sample may also lose its solution to cheirality.
    assert np.mean(np.isfinite(best)) > 0.99
    best = best[np.isfinite(best)]
    assert np.median(best) < 1e-4
    assert np.quantile(best, 0.95) < 1e-3


# ---- degenerate input -------------------------------------------------------------------------

TRUTH = relpose_from_planar_params(0.3, 0.7)
X_GOOD = np.array([[1.0, -0.5, 6.0], [-2.0, 0.8, 9.0]])


def project(pose: Pose, X: np.ndarray) -> np.ndarray:
    Y = pose.transform(X)
    return Y / Y[:, 2:]


def test_reference_example_has_the_truth() -> None:
    sols = relpose_planar_2p(X_GOOD / X_GOOD[:, 2:], project(TRUTH, X_GOOD))
    assert min(pose_error(p, TRUTH.R, TRUTH.t) for p in sols) < EXACT


def test_repeated_point_gives_no_solution() -> None:
    xq, xr = X_GOOD / X_GOOD[:, 2:], project(TRUTH, X_GOOD)
    assert relpose_planar_2p(xq[[0, 0]], xr[[0, 0]]) == []
    assert relpose_planar_2p(xq[[1, 1]], 2.0 * xr[[1, 1]]) == []  # proportional rows


def test_points_on_the_horizon_row_give_no_solution() -> None:
    """y = 0 in both views (points at camera height): each match constrains nothing."""
    X = X_GOOD.copy()
    X[:, 1] = 0.0
    xq, xr = X / X[:, 2:], project(TRUTH, X)
    assert np.all(xr[:, 1] == 0.0)
    assert relpose_planar_2p(xq, xr) == []
    X = X_GOOD.copy()
    X[0, 1] = 0.0  # only one of the two: one equation left, a one-parameter family
    assert relpose_planar_2p(X / X[:, 2:], project(TRUTH, X)) == []


def test_zero_baseline_gives_no_solution() -> None:
    rotation_only = relpose_from_planar_params(0.3, 0.7, 0.0)
    assert relpose_planar_2p(X_GOOD / X_GOOD[:, 2:], project(rotation_only, X_GOOD)) == []
    xq = X_GOOD / X_GOOD[:, 2:]
    assert relpose_planar_2p(xq, xq) == []  # identity


@pytest.mark.parametrize("distance", [1e6, 1e9, 1e12])
def test_points_at_infinity_give_no_solution(distance: float) -> None:
    X = X_GOOD * distance
    assert relpose_planar_2p(X / X[:, 2:], project(TRUTH, X)) == []


def test_identical_rays_after_rotation_give_no_solution() -> None:
    xq = X_GOOD / X_GOOD[:, 2:]
    y = xq @ TRUTH.R.T  # x_ref = R x_query: both points at infinity
    assert relpose_planar_2p(xq, y / y[:, 2:]) == []


def test_degenerate_samples_in_a_batch_are_invalid_rows() -> None:
    xq, xr = X_GOOD / X_GOOD[:, 2:], project(TRUTH, X_GOOD)
    y = xq @ TRUTH.R.T
    batch_q = np.stack([xq, xq[[0, 0]], xq])
    batch_r = np.stack([xr, xr[[0, 0]], y / y[:, 2:]])
    _, _, valid = relpose_planar_2p_batch(batch_q, batch_r)
    assert valid[0].any() and not valid[1].any() and not valid[2].any()


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ([[np.nan, 0.0, 1.0], [0.1, 0.2, 1.0]], r"x_query: contains NaN or inf \(first at index \(0, 0\)\)"),
        ([[0.0, 0.0, 1.0], [0.1, np.inf, 1.0]], r"x_query: contains NaN or inf \(first at index \(1, 1\)\)"),
        (np.zeros((3, 3)), r"x_query: expected shape \(2, 3\), got \(3, 3\)"),
        (np.zeros((2, 4)), r"x_query: expected shape \(2, 3\), got \(2, 4\)"),
        (np.zeros(6), r"x_query: expected shape \(2, 3\), got \(6,\)"),
        ("two points", "x_query: expected a numeric array"),
    ],
)
def test_invalid_input_raises_value_error_with_a_clear_message(bad, message: str) -> None:
    xr = project(TRUTH, X_GOOD)
    with pytest.raises(ValueError, match=message):
        relpose_planar_2p(bad, xr)


def test_invalid_reference_and_batch_input() -> None:
    xq = X_GOOD / X_GOOD[:, 2:]
    with pytest.raises(ValueError, match=r"x_ref: expected shape \(2, 3\)"):
        relpose_planar_2p(xq, np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"x_query: expected shape \(N, 2, 3\)"):
        relpose_planar_2p_batch(xq, xq)
    with pytest.raises(ValueError, match="different numbers of samples"):
        relpose_planar_2p_batch(np.stack([xq] * 3), np.stack([xq] * 2))
    with pytest.raises(ValueError, match="NaN or inf"):
        relpose_planar_2p_batch(np.full((4, 2, 3), np.nan), np.ones((4, 2, 3)))


def test_zero_rays_are_degenerate_input_with_no_solution() -> None:
    """All-zero rays are finite arrays of the right shape, so not invalid input (that raises):
    degenerate input, for which the contract is an empty list (and invalid batch rows)."""
    xr = project(TRUTH, X_GOOD)
    assert relpose_planar_2p(np.zeros((2, 3)), xr) == []
    assert relpose_planar_2p(xr, np.zeros((2, 3))) == []
    _, _, valid = relpose_planar_2p_batch(np.zeros((1, 2, 3)), xr[None])
    assert not valid.any()


# ---- peer libraries ---------------------------------------------------------------------------


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.mark.parametrize("seed", SEEDS)
def test_cross_check_with_poselib(seed: int) -> None:
    """PoseLib ``relpose_upright_planar_2pt(x1, x2)`` with ``x2 = R x1 + t`` (CameraPose is
    ``cam2_from_cam1``), i.e. x1 = query, x2 = reference, same convention as ours.

    PoseLib's cheirality test assumes **unit** bearing vectors (with (x, y, 1) input it
    discards true solutions), so bearings are normalised for it. On exact data it returns the
    same solution set as ours: the true pose plus, for most samples, the second root.
    """
    poselib = pytest.importorskip("poselib")
    rng = np.random.default_rng(300 + seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 400)
    extra = 0
    for i in range(len(theta)):
        ours = relpose_planar_2p(xq[i], xr[i])
        theirs = poselib.relpose_upright_planar_2pt(_unit(xq[i]), _unit(xr[i]))
        assert min(pose_error(p, R[i], t[i]) for p in ours) < EXACT
        assert min(pose_error(p, R[i], t[i]) for p in theirs) < 1e-6
        for p in ours:
            assert min(pose_error(p, q.R, q.t) for q in theirs) < 1e-6
        extra += len(theirs) - len(ours)
    assert extra == 0


@pytest.mark.parametrize("seed", SEEDS)
def test_cross_check_with_opencv_essential_and_recover_pose(seed: int) -> None:
    """OpenCV (5-point RANSAC + recoverPose, points2ᵀ E points1 = 0, x2 = R x1 + t) on 12 points of a
    planar scene; our solutions from any two of the points contain OpenCV's pose."""
    cv2 = pytest.importorskip("cv2")
    cv2.setRNGSeed(seed)
    rng = np.random.default_rng(400 + seed)
    theta, phi, R, t, xq, xr, _ = planar_scenes(rng, 30, n_points=12, min_depth=0.5)
    for i in range(len(theta)):
        p1 = np.ascontiguousarray(xq[i, :, :2])
        p2 = np.ascontiguousarray(xr[i, :, :2])
        E, mask = cv2.findEssentialMat(p1, p2, np.eye(3), cv2.RANSAC, 0.999, 1e-7)
        assert E is not None and E.shape[1] == 3
        found = None
        for k in range(E.shape[0] // 3):
            _, Rc, tc, _ = cv2.recoverPose(E[3 * k : 3 * k + 3], p1, p2, np.eye(3))
            if pose_error(Pose(Rc, tc.ravel()), R[i], t[i]) < 1e-5:
                found = Pose(Rc, tc.ravel())
        assert found is not None, "OpenCV did not recover the true pose"
        for a, b in [(0, 1), (3, 7), (10, 11)]:
            ours = relpose_planar_2p(xq[i, [a, b]], xr[i, [a, b]])
            assert min(pose_error(p, found.R, found.t) for p in ours) < 1e-5
