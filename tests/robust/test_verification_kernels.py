"""Direct tests of the compiled verification and refinement kernels (issue 10: the per-estimate
verification runs in numba). Each is checked against an independent computation: finite
differences, explicit leave-one-out refinements, numpy's linear algebra. Generated data only."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.mat3 import sym_eigvals
from planarloc.geometry.pose import Pose
from planarloc.robust import observability as obs
from planarloc.robust.estimators import SIGMA_FLOOR_PX, Planar2p1pEstimator
from planarloc.robust.final_refinement import refine_until_stable
from planarloc.robust.jackknife import reference_jackknife
from planarloc.robust.options import RansacOptions
from planarloc.robust.problem import build_problem
from planarloc.robust.refinement import (
    RefineSettings,
    StartPose,
    map_centre_covariance,
    map_uncertainty_covariance,
    refine_pose,
    residuals,
    residuals_jacobian,
)
from planarloc.robust.scoring import errors_sq

NO3D = np.zeros(0, dtype=np.int64)
FREE = np.zeros(6, dtype=np.bool_)


def problem_with_points(sc, rng: np.random.Generator, n3d: int = 4):
    """The scene's problem plus ``n3d`` exact 2D-3D constraints in front of the query."""
    pb = build_problem(sc.query_camera, sc.pairs)
    Xc = np.column_stack([rng.uniform(-2, 2, n3d), rng.uniform(-1, 1, n3d), rng.uniform(4, 9, n3d)])
    X = (Xc - sc.query_pose.t) @ sc.query_pose.R  # camera -> world
    return pb.with_points3d(Xc / Xc[:, 2:], X, np.full(n3d, -1))


def refine_to_convergence(pb, pose: Pose, idx2d: np.ndarray, idx3d: np.ndarray = NO3D) -> Pose:
    start = StartPose(pose.R, pose.center, np.eye(3), FREE)
    R, t, *_ = refine_pose(start, pb.arrays, idx2d, idx3d, RefineSettings(4.0, 2.0, 60, 0.5, 0.0, 0.0))
    return Pose(R, t)


def test_jacobian_matches_finite_differences(scene) -> None:
    sc = scene(11, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.0)
    rng = np.random.default_rng(0)
    pb = problem_with_points(sc, rng)
    idx2d, idx3d = np.arange(len(pb.xq)), np.arange(len(pb.X3d))
    m = len(idx2d) + 2 * len(idx3d)
    B = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R, c = sc.query_pose.R, sc.query_pose.center + 0.05
    r, J, Jrot = np.empty(m), np.empty((m, 6)), np.empty((m, 3))
    residuals_jacobian(R, c, B, pb.arrays, idx2d, idx3d, r, J, Jrot)
    base = np.empty(m)
    residuals(np.zeros(6), R, c, B, pb.arrays, idx2d, idx3d, base)
    np.testing.assert_allclose(r, base, rtol=1e-10, atol=1e-10)
    h = 1e-6
    for k in range(6):  # query parameters: rotation increment, centre along B's columns
        step = np.zeros(6)
        step[k] = h
        plus, minus = np.empty(m), np.empty(m)
        residuals(step, R, c, B, pb.arrays, idx2d, idx3d, plus)
        residuals(-step, R, c, B, pb.arrays, idx2d, idx3d, minus)
        np.testing.assert_allclose(
            J[:, k], (plus - minus) / (2 * h), rtol=1e-4, atol=1e-4 * np.abs(J[:, k]).max()
        )
    for k in range(3):  # a rotation increment of each 2D-2D row's own reference, centre fixed
        fd = np.empty(len(idx2d))
        for p in range(pb.num_pairs):
            rows = np.flatnonzero(pb.pair == p)
            out = []
            for sgn in (1.0, -1.0):
                w = np.zeros(3)
                w[k] = sgn * h
                Rp = pb.ref_R.copy()
                tp = pb.ref_t.copy()
                Rp[p] = Rotation.from_rotvec(w).as_matrix() @ pb.ref_R[p]
                tp[p] = -Rp[p] @ (-pb.ref_R[p].T @ pb.ref_t[p])
                e = np.empty(m)
                residuals(np.zeros(6), R, c, B, pb.arrays._replace(ref_R=Rp, ref_t=tp), idx2d, idx3d, e)
                out.append(e[rows])
            fd[rows] = (out[0] - out[1]) / (2 * h)
        np.testing.assert_allclose(Jrot[: len(idx2d), k], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())
    assert np.all(Jrot[len(idx2d) :] == 0.0)  # world points do not move with a reference


def test_map_propagation_predicts_the_refined_shift(scene) -> None:
    """First-order propagation of a reference-pose error = how far the refined query moves."""
    sc = scene(12, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    idx2d = np.arange(len(pb.xq))
    H, M, _ = map_uncertainty_covariance(
        sc.query_pose.R, sc.query_pose.t, pb.arrays, idx2d, NO3D, 2.0, 1.0, 1.0
    )
    # The refined query cancels the residual change: J δq + J_r δr = 0, so δq = -H⁻¹ M δr
    # (noise-free data: W = I). The covariance B diag(var) Bᵀ does not see the sign.
    Bm = -np.linalg.solve(H, M)
    p, h = 1, 1e-5
    c_ref = -pb.ref_R[p].T @ pb.ref_t[p]
    for k in range(6):
        Rp, tp = pb.ref_R.copy(), pb.ref_t.copy()
        if k < 3:
            w = np.zeros(3)
            w[k] = h
            Rp[p] = Rotation.from_rotvec(w).as_matrix() @ pb.ref_R[p]
            tp[p] = -Rp[p] @ c_ref
        else:
            dc = np.zeros(3)
            dc[k - 3] = h
            tp[p] = -pb.ref_R[p] @ (c_ref + dc)
        moved = refine_to_convergence(
            replace(pb, arrays=pb.arrays._replace(ref_R=Rp, ref_t=tp)), sc.query_pose, idx2d
        )
        shift = (moved.center - sc.query_pose.center) / h
        np.testing.assert_allclose(
            shift, Bm[3:, 6 * p + k], rtol=2e-3, atol=2e-3 * np.abs(Bm[3:, 6 * p + k]).max()
        )


def test_map_centre_covariance_matches_numpy(scene) -> None:
    sc = scene(12, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    args = (
        sc.query_pose.R,
        sc.query_pose.t,
        pb.arrays,
        np.arange(len(pb.xq)),
        NO3D,
        2.0,
        np.radians(0.1),
        0.05,
    )
    H, M, var = map_uncertainty_covariance(*args)
    Bm = np.linalg.solve(H, M)
    np.testing.assert_allclose(map_centre_covariance(H, M, var), ((Bm * var) @ Bm.T)[3:, 3:], rtol=1e-9)


def test_jackknife_matches_explicit_leave_one_out(scene) -> None:
    sc = scene(13, num_refs=4, matches_per_pair=40, noise_px=1.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    est = Planar2p1pEstimator(pb, RansacOptions(threshold_px=2.0))
    full = refine_to_convergence(pb, sc.query_pose, np.arange(len(pb.xq)))
    in2d, in3d = est.inliers(full.R, full.t)
    jk = reference_jackknife(est, full.R, full.t, in2d, in3d, max_iterations=40)
    centres, rots = [], []
    for k in range(pb.num_pairs):
        keep = in2d.copy()
        keep[pb.offsets[k] : pb.offsets[k + 1]] = False
        loo = refine_to_convergence(pb, full, np.flatnonzero(keep))
        centres.append(loo.center)
        rots.append(np.degrees(Rotation.from_matrix(loo.R @ full.R.T).magnitude()))
    centres = np.array(centres)
    d = centres - centres.mean(axis=0)
    n = len(centres)
    std = np.sqrt(np.linalg.eigvalsh((n - 1) / n * d.T @ d).max())
    shifts = np.linalg.norm(centres - full.center, axis=1)
    assert jk.num_references == n
    assert jk.position_std_m == pytest.approx(std, rel=1e-4)
    assert jk.max_shift_m == pytest.approx(shifts.max(), rel=1e-4)
    assert jk.max_rotation_deg == pytest.approx(max(rots), rel=1e-3, abs=1e-6)
    assert jk.worst_reference == int(np.argmax(shifts))
    # Two steps (the default) already land within a few percent of the converged spread.
    assert reference_jackknife(est, full.R, full.t, in2d, in3d).position_std_m == pytest.approx(std, rel=0.1)


def test_pose_support_numbers(scene) -> None:
    sc = scene(14, num_refs=4, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.3)
    pb = build_problem(sc.query_camera, sc.pairs)
    in2d = ~np.concatenate(sc.is_outlier)
    in2d[pb.offsets[2] : pb.offsets[2] + 27] = False  # pair 2 keeps at most 3 inliers: not supporting
    g_world = np.array([0.0, 1.0, 0.0])
    g_query = np.array([0.0, np.cos(0.03), np.sin(0.03)])
    R, t, c = sc.query_pose.R, sc.query_pose.t, sc.query_pose.center
    s = obs.pose_support(pb, R, t, in2d, g_world, g_query)
    counts = np.array([in2d[pb.offsets[p] : pb.offsets[p + 1]].sum() for p in range(pb.num_pairs)])
    np.testing.assert_array_equal(s.pair_inliers, counts)
    np.testing.assert_array_equal(s.supporting, np.flatnonzero(counts >= obs.MIN_PAIR_INLIERS))
    centres = obs.reference_centres(pb)
    pts = np.vstack([c, centres[s.supporting]])
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    assert s.collinearity == pytest.approx(sv[1] / sv[0], rel=1e-9)
    assert s.median_distance_m == pytest.approx(np.median(np.linalg.norm(centres[counts > 0] - c, axis=1)))
    g_pred = R @ g_world
    assert s.fit.tilt_deg == pytest.approx(np.degrees(np.arccos(g_pred @ g_query)), abs=1e-6)
    b = c - centres[s.supporting]
    h = b @ g_world
    horizontal = np.sqrt((b * b).sum(axis=1) - h * h)
    assert s.fit.elevation_deg == pytest.approx(
        np.degrees(np.arctan2(abs(np.median(h)), np.median(horizontal)))
    )
    # Reference centres on the line through the query: collinearity 0.
    line = Pose.from_center(np.eye(3), c + np.array([1.0, 0.0, 0.0]))
    pb_line = replace(
        pb,
        arrays=pb.arrays._replace(
            ref_R=np.array([np.eye(3)] * pb.num_pairs),
            ref_t=np.array([-(c + (k + 1) * (line.center - c)) for k in range(pb.num_pairs)]),
        ),
    )
    assert obs.pose_support(pb_line, R, t, ~np.zeros(len(in2d), bool), g_world, g_world).collinearity < 1e-7


def test_refine_until_stable_returns_consistent_inliers_and_score(scene) -> None:
    sc = scene(15, num_refs=3, matches_per_pair=40, noise_px=1.0, outlier_ratio=0.5)
    pb = build_problem(sc.query_camera, sc.pairs)
    rng = np.random.default_rng(5)
    start = Pose.from_center(
        Rotation.from_rotvec(rng.normal(0, 0.003, 3)).as_matrix() @ sc.query_pose.R,
        sc.query_pose.center + rng.normal(0, 0.03, 3),
    )
    th2 = 4.0
    R, t, H, sigma, cost, in2d, in3d, score, _ = refine_until_stable(
        start.R, start.t, pb.arrays, RefineSettings(th2, 2.0, 6, SIGMA_FLOOR_PX, 0.0, 0.0), 4
    )
    e2d, _ = errors_sq(R, t, pb.arrays)
    np.testing.assert_array_equal(in2d, e2d < th2)
    assert score == pytest.approx(np.minimum(e2d, th2).sum(), rel=1e-12)
    e_start, _ = errors_sq(start.R, start.t, pb.arrays)
    assert score < np.minimum(e_start, th2).sum()
    assert np.linalg.norm(-R.T @ t - sc.query_pose.center) < np.linalg.norm(
        start.center - sc.query_pose.center
    )
    assert sigma >= SIGMA_FLOOR_PX and np.all(np.linalg.eigvalsh(H) > 0) and np.isfinite(cost)


@pytest.mark.parametrize("seed", range(6))
def test_sym_eigvals_match_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    A = A + A.T
    if seed == 4:  # a repeated eigenvalue
        Q = np.linalg.qr(A)[0]
        A = Q @ np.diag([2.0, 2.0, -1.0]) @ Q.T
    if seed == 5:
        A = np.eye(3) * 3.0
    np.testing.assert_allclose(
        sorted(sym_eigvals(A)), np.linalg.eigvalsh(A), atol=1e-9 * max(1.0, np.abs(A).max())
    )
