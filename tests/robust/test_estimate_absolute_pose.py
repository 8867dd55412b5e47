"""Ground-truth recovery of :func:`estimate_absolute_pose` on the paper's synthetic protocol."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import pose_errors
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions

ALL_METHODS = ("2p1p", "2p2p", "5p5p-nister", "5p5p-stewenius", "8p8p")
PLANAR_METHODS = ("2p1p", "2p2p")
PAPER_ITERATIONS = dict(max_iterations=100, min_iterations=100)


@pytest.mark.parametrize("method", ALL_METHODS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_free_recovery_is_exact(scene, pose_errors_precise, method: str, seed: int) -> None:
    sc = scene(seed, num_refs=5, matches_per_pair=50, noise_px=0.0)
    est = estimate_absolute_pose(
        sc.query_camera, sc.pairs, method, RansacOptions(**PAPER_ITERATIONS, seed=seed)
    )
    assert est.success, est.message
    dc, dr = pose_errors_precise(est.pose, sc.query_pose)
    assert dc < 1e-6 and dr < 1e-6
    assert est.num_inliers == 250
    assert all(m.all() for m in est.inliers)


@pytest.mark.parametrize("method", PLANAR_METHODS)
def test_noise_and_outliers_success_rate(scene, method: str) -> None:
    """1 px noise, 40% outliers, 100 fixed iterations: the paper's success criterion on >= 9/10."""
    ok = 0
    for seed in range(10):
        sc = scene(100 + seed, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.4)
        est = estimate_absolute_pose(
            sc.query_camera, sc.pairs, method, RansacOptions(**PAPER_ITERATIONS, seed=seed)
        )
        if est.success:
            dc, dr = pose_errors(est.pose, sc.query_pose)
            ok += dc < 0.1 and dr < 1.0
    assert ok >= 9


@pytest.mark.parametrize("method", PLANAR_METHODS)
def test_inliers_separate_outliers(scene, method: str) -> None:
    sc = scene(100, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.4)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, method, RansacOptions(**PAPER_ITERATIONS))
    assert est.success
    assert [len(m) for m in est.inliers] == [len(p) for p in sc.pairs]
    inl = np.concatenate(est.inliers)
    out = np.concatenate(sc.is_outlier)
    assert est.num_inliers == inl.sum()
    # Most true inliers found (2 px threshold at 1 px noise); few outliers accepted (an
    # outlier close to its epipolar line is indistinguishable from an inlier).
    assert inl[~out].mean() > 0.8
    assert inl[out].mean() < 0.1


@pytest.mark.parametrize("method", ALL_METHODS)
def test_same_seed_same_pose(scene, method: str) -> None:
    sc = scene(7, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.3)
    opts = RansacOptions(**PAPER_ITERATIONS, seed=1234)
    a = estimate_absolute_pose(sc.query_camera, sc.pairs, method, opts)
    b = estimate_absolute_pose(sc.query_camera, sc.pairs, method, opts)
    assert a.status == b.status
    pa, pb = a.pose or a.unreliable_pose, b.pose or b.unreliable_pose
    assert pa is not None and pb is not None
    np.testing.assert_array_equal(pa.R, pb.R)
    np.testing.assert_array_equal(pa.t, pb.t)
    for ma, mb in zip(a.inliers, b.inliers):
        np.testing.assert_array_equal(ma, mb)
    assert a.stats.hypotheses == b.stats.hypotheses and a.stats.scored == b.stats.scored


def test_seed_changes_samples(scene) -> None:
    sc = scene(7, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.3)
    a, b = (
        estimate_absolute_pose(
            sc.query_camera, sc.pairs, "2p1p", RansacOptions(**PAPER_ITERATIONS, seed=s, refine=False)
        )
        for s in (1, 2)
    )
    assert a.stats.hypotheses != b.stats.hypotheses or not np.array_equal(a.pose.t, b.pose.t)


@pytest.mark.parametrize("method", PLANAR_METHODS)
def test_reference_depth_gives_2d3d_inliers(scene, method: str) -> None:
    sc = scene(11, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.2, with_depth=True)
    with_depth = sum(int(np.isfinite(p.ref_points3d[:, 0]).sum()) for p in sc.pairs)
    assert with_depth == 200  # outliers have no depth in the generator
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, method, RansacOptions(**PAPER_ITERATIONS))
    assert est.success, est.message
    # Exact depth, 1 px noise on the query only: P(|noise| < 2 px) = 1 - exp(-2) = 0.86.
    assert est.num_inliers_3d >= 0.75 * with_depth
    dc, dr = pose_errors(est.pose, sc.query_pose)
    assert dc < 0.1 and dr < 1.0


def test_total_time_spans_the_whole_call(scene, monkeypatch) -> None:
    """``stats.time_s["total"]`` is the whole call, the short 6DoF check after the judgement
    included (it was written by the judgement, a third of the call short of it)."""
    sc = scene(0, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.2)
    readings: list[float] = []

    def clock() -> float:  # every reading one unit after the previous one
        readings.append(float(len(readings)))
        return readings[-1]

    monkeypatch.setattr("time.perf_counter", clock)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", RansacOptions(**PAPER_ITERATIONS))
    assert est.success, est.message
    assert est.stats.time_s["cross_check"] > 0  # the check ran after the judgement
    assert est.stats.time_s["total"] == readings[-1] - readings[0]


def test_statistics_and_result_summary(scene) -> None:
    sc = scene(0, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.2)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "2p1p", RansacOptions(**PAPER_ITERATIONS))
    assert est.success and est.iterations == 100 == est.stats.iterations
    assert est.stats.local_optimizations >= 1
    assert {"hypotheses", "scoring", "refinement", "total"} <= set(est.stats.time_s)
    assert 0 < est.position_std_m < 0.25
    d = est.to_dict()
    assert d["success"] and d["num_matches"] == [50] * 5 and len(d["quat_wxyz"]) == 4


def test_adaptive_termination_on_clean_data(scene) -> None:
    sc = scene(0, num_refs=5, matches_per_pair=50, noise_px=0.5)
    est = estimate_absolute_pose(
        sc.query_camera, sc.pairs, "2p1p", RansacOptions(max_iterations=10_000, min_iterations=1)
    )
    assert est.success
    assert est.iterations < 200
