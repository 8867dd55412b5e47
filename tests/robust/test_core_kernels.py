"""Direct tests of the robust core's parts (scoring, refinement, sampling, structure), which
the estimator tests only reach through the whole pipeline. Generated data only."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import Pose
from planarloc.robust.problem import build_problem
from planarloc.robust.refinement import (
    RefineSettings,
    StartPose,
    centre_covariance,
    refine_on_inliers,
    refine_pose,
)
from planarloc.robust.sampling import draw_pair_samples, draw_within_pairs, eligible_pairs
from planarloc.robust.scoring import errors_sq, msac_scores
from planarloc.robust.structure import triangulate_tracks


def perturbed(pose: Pose, rng: np.random.Generator, rot: float, pos: float) -> Pose:
    from scipy.spatial.transform import Rotation

    dR = Rotation.from_rotvec(rng.normal(0, rot, 3)).as_matrix()
    return Pose.from_center(dR @ pose.R, pose.center + rng.normal(0, pos, 3))


def sampson_sq_reference(pb, pose: Pose) -> np.ndarray:
    """Squared Sampson errors in pixels, written independently with numpy."""
    out = np.empty(len(pb.xq))
    for p in range(pb.num_pairs):
        R = pb.ref_R[p] @ pose.R.T
        t = pb.ref_t[p] - R @ pose.t
        E = np.cross(t, R.T).T  # [t]x R
        sl = slice(pb.offsets[p], pb.offsets[p + 1])
        q, r = pb.xq[sl], pb.xr[sl]
        Eq, Etr = q @ E.T, r @ E
        num = np.einsum("ni,ni->n", r, Eq) ** 2
        den = (
            (Eq[:, 0] / pb.f_ref[p, 0]) ** 2
            + (Eq[:, 1] / pb.f_ref[p, 1]) ** 2
            + (Etr[:, 0] / pb.f_query[0]) ** 2
            + (Etr[:, 1] / pb.f_query[1]) ** 2
        )
        out[sl] = num / den
    return out


# ---- scoring ------------------------------------------------------------------------------------
def test_errors_match_reference_and_vanish_at_truth(scene) -> None:
    sc = scene(1, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.25)
    pb = build_problem(sc.query_camera, sc.pairs)
    e2d, _ = errors_sq(sc.query_pose.R, sc.query_pose.t, pb.arrays)
    inl = ~np.concatenate(sc.is_outlier)
    assert e2d[inl].max() < 1e-12 and np.median(e2d[~inl]) > 4.0
    wrong = perturbed(sc.query_pose, np.random.default_rng(0), 0.02, 0.3)
    e_wrong, _ = errors_sq(wrong.R, wrong.t, pb.arrays)
    np.testing.assert_allclose(e_wrong, sampson_sq_reference(pb, wrong), rtol=1e-9)


def test_msac_cost_and_bound(scene) -> None:
    sc = scene(2, num_refs=3, matches_per_pair=40, noise_px=1.0, outlier_ratio=0.5)
    pb = build_problem(sc.query_camera, sc.pairs)
    rng = np.random.default_rng(1)
    poses = [sc.query_pose] + [perturbed(sc.query_pose, rng, 0.05, 1.0) for _ in range(7)]
    R = np.ascontiguousarray([p.R for p in poses])
    t = np.ascontiguousarray([p.t for p in poses])
    th2 = 4.0
    cost, inl = msac_scores(R, t, len(R), pb.arrays, th2)
    exact = np.array([np.minimum(errors_sq(p.R, p.t, pb.arrays)[0], th2).sum() for p in poses])
    count = np.array([(errors_sq(p.R, p.t, pb.arrays)[0] < th2).sum() for p in poses])
    best = np.inf
    for k in range(len(poses)):
        if exact[k] < best:  # a new running best is scored in full
            assert cost[k] == pytest.approx(exact[k], rel=1e-12) and inl[k] == count[k]
            best = exact[k]
        else:  # scoring stopped early: a lower bound that still exceeds the running best
            assert best < cost[k] <= exact[k] + 1e-9
    assert np.argmin(cost) == np.argmin(exact) == 0  # the truth wins
    # An external bound below every cost prunes all of them without changing the argmin.
    cost_b, _ = msac_scores(R, t, len(R), pb.arrays, th2, 0.5 * exact.min())
    assert np.all(cost_b > 0.5 * exact.min()) and np.all(cost_b <= exact + 1e-9)


# ---- refinement -----------------------------------------------------------------------------------
def test_refine_pose_converges_to_truth_on_exact_inliers(scene) -> None:
    sc = scene(3, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    start = perturbed(sc.query_pose, np.random.default_rng(2), 0.01, 0.1)
    idx = np.arange(len(pb.xq))
    R, t, H, sigma, cost = refine_pose(
        StartPose(start.R, start.center, np.eye(3), np.zeros(6, dtype=np.bool_)),
        pb.arrays,
        idx,
        np.zeros(0, dtype=np.int64),
        RefineSettings(4.0, 2.0, 20, 0.5, 0.0, 0.0),
    )
    assert np.linalg.norm(-R.T @ t - sc.query_pose.center) < 1e-6 and np.abs(R - sc.query_pose.R).max() < 1e-7
    assert cost < 1e-9 and sigma == 0.5  # residual scale floored at sigma_floor
    assert np.all(np.linalg.eigvalsh(H) > 0)


def test_refine_on_inliers_masks_and_too_few(scene) -> None:
    sc = scene(4, num_refs=3, matches_per_pair=40, noise_px=1.0, outlier_ratio=0.5)
    pb = build_problem(sc.query_camera, sc.pairs)
    start = perturbed(sc.query_pose, np.random.default_rng(3), 0.002, 0.02)
    R, t, H, sigma, cost, in2d, in3d = refine_on_inliers(
        start.R, start.t, pb.arrays, RefineSettings(4.0, 2.0, 6, 0.5, 0.0, 0.0)
    )
    e, _ = errors_sq(start.R, start.t, pb.arrays)
    np.testing.assert_array_equal(in2d, e < 4.0)
    e_new, _ = errors_sq(R, t, pb.arrays)

    def cauchy(err_sq: np.ndarray) -> float:  # the refinement's loss, scale 2 px, on the initial inliers
        return float(0.5 * 4.0 * np.log1p(err_sq[in2d] / 4.0).sum())

    assert cost == pytest.approx(cauchy(e_new), rel=1e-9) and cost < cauchy(e)
    far = perturbed(sc.query_pose, np.random.default_rng(4), 0.5, 5.0)
    R2, t2, _, _, cost2, in2, _ = refine_on_inliers(
        far.R, far.t, pb.arrays, RefineSettings(1e-12, 2.0, 6, 0.5, 0.0, 0.0)
    )
    assert not in2.any() and cost2 == np.inf and np.array_equal(R2, far.R) and np.array_equal(t2, far.t)


def test_centre_covariance() -> None:
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    H = A @ A.T + 0.1 * np.eye(6)
    np.testing.assert_allclose(centre_covariance(H, 2.0), 4.0 * np.linalg.inv(H)[3:, 3:], rtol=1e-9)
    H[:, 5] = H[5, :] = 0.0
    assert np.isinf(centre_covariance(H, 1.0)).all()


# ---- sampling ------------------------------------------------------------------------------------
def test_draw_pair_samples_rows_and_weights() -> None:
    offsets = np.array([0, 10, 40, 41, 101], dtype=np.int64)  # pair 2 has one match
    S = 20000
    u = np.random.default_rng(6).random((S, 5))
    samples, pj, pk = (
        np.empty((S, 3), dtype=np.int64),
        np.empty(S, dtype=np.int64),
        np.empty(S, dtype=np.int64),
    )
    draw_pair_samples(u, offsets, 2, 1, samples, pj, pk)
    assert np.all(pj != pk) and np.all(pj != 2)  # pair 2 cannot give two matches
    assert np.all((samples[:, 0] >= offsets[pj]) & (samples[:, 1] < offsets[pj + 1]))
    assert np.all((samples[:, 2] >= offsets[pk]) & (samples[:, 2] < offsets[pk + 1]))
    assert np.all(samples[:, 0] != samples[:, 1])
    freq = np.bincount(pj, minlength=4) / S  # proportional to the matches of eligible pairs
    np.testing.assert_allclose(freq[[0, 1, 3]], np.array([10, 30, 60]) / 100, atol=0.015)


def test_draw_within_pairs_distinct_and_uniform() -> None:
    offsets = np.array([0, 5, 25], dtype=np.int64)
    S = 20000
    sp = np.full(S, 1, dtype=np.int64)
    samples = np.empty((S, 3), dtype=np.int64)
    draw_within_pairs(np.random.default_rng(7).random((S, 3)), offsets, sp, 3, samples)
    assert np.all((samples >= 5) & (samples < 25))
    assert np.all(np.diff(np.sort(samples, axis=1), axis=1) > 0)
    np.testing.assert_allclose(np.bincount(samples.ravel() - 5) / (3 * S), 1 / 20, atol=0.006)


def test_eligible_pairs() -> None:
    assert eligible_pairs(np.array([2, 1]), 2, 1) and not eligible_pairs(np.array([2, 0]), 2, 1)
    assert not eligible_pairs(np.array([5]), 2, 1) and eligible_pairs(np.array([5, 5]), 5, 5)


# ---- structure -----------------------------------------------------------------------------------
def test_triangulate_tracks_recovers_points(scene) -> None:
    sc = scene(8, num_refs=3, matches_per_pair=60, noise_px=0.0, outlier_ratio=0.0, track_pool=1.5)
    pb = build_problem(sc.query_camera, sc.pairs)
    xq3, X3, C3, views, jac = triangulate_tracks(pb, 2.0, 1.0)
    ids, counts = np.unique(pb.query_ids, return_counts=True)
    assert 0 < len(X3) <= (counts >= 2).sum()
    # Two different references triangulated each point; moving both of their centres by d moves it by d.
    assert (
        views.shape == (len(X3), 2)
        and np.all((views >= 0) & (views < pb.num_pairs))
        and np.all(views[:, 0] != views[:, 1])
    )
    np.testing.assert_allclose(
        jac[:, 0, :, 3:] + jac[:, 1, :, 3:], np.broadcast_to(np.eye(3), (len(X3), 3, 3)), atol=1e-9
    )
    # Each triangulated point is a true scene point seen by the query along its ray.
    d = np.linalg.norm(X3[:, None] - sc.points[ids[counts >= 2]][None], axis=2).min(axis=1)
    assert d.max() < 1e-6
    Xc = X3 @ sc.query_pose.R.T + sc.query_pose.t
    np.testing.assert_allclose(Xc[:, :2] / Xc[:, 2:], xq3[:, :2] / xq3[:, 2:], atol=1e-9)
    # Without ids there are no tracks.
    none = build_problem(
        sc.query_camera, [type(p)(p.ref_pose, p.ref_camera, p.query_points, p.ref_points) for p in sc.pairs]
    )
    assert len(triangulate_tracks(none, 2.0, 1.0)[1]) == 0
