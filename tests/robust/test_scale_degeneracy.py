"""Collinear geometry (straight corridor / road): the position along the line is unobservable
from 2D-2D constraints. It must be reported as ``degenerate_scale``, never as a wrong success;
``structure="tracks"`` (or reference depth) must solve it."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import pose_errors
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions

ALL_METHODS = ("2p1p", "2p2p", "5p5p-nister", "5p5p-stewenius", "8p8p")
SEEDS = range(4)
COLLINEAR = dict(num_refs=5, matches_per_pair=100, collinear=True, track_pool=2)


def collinear_estimates(scene, method: str, noise_px: float, structure: str = "none"):
    """(seed, scene, estimate) of the collinear scene of each seed, 100 RANSAC iterations."""
    for seed in SEEDS:
        sc = scene(seed, noise_px=noise_px, **COLLINEAR)
        options = RansacOptions(max_iterations=100, min_iterations=100, structure=structure, seed=seed)
        yield seed, sc, estimate_absolute_pose(sc.query_camera, sc.pairs, method, options)


CASES = [(m, n) for n in (0.0, 1.0) for m in ALL_METHODS if (m, n) != ("8p8p", 0.0)]


@pytest.mark.parametrize("method, noise_px", CASES)
def test_collinear_without_structure_is_degenerate(scene, method: str, noise_px: float) -> None:
    for seed, sc, est in collinear_estimates(scene, method, noise_px):
        assert not est.success, (
            f"seed {seed}: reported success, centre error {pose_errors(est.pose, sc.query_pose)[0]:.3f} m"
        )
        assert est.status == "degenerate_scale", est.message
        assert est.pose is None
        assert est.unreliable_pose is not None
        assert "tracks" in est.message  # the hint to the remedy
        assert est.num_inliers > 0 and est.num_inliers_3d == 0


def test_exact_collinear_8p8p_reports_degenerate_without_a_hypothesis(scene) -> None:
    """Noise-free 8p8p: every relative pose is exact, every triangulation singular (eq. 15)."""
    for _seed, _sc, est in collinear_estimates(scene, "8p8p", 0.0):
        assert not est.success and est.pose is None
        assert est.status == "degenerate_scale", est.message
        assert est.stats.rejected_degenerate > 0 and "tracks" in est.message


@pytest.mark.parametrize("method", ALL_METHODS)
def test_collinear_never_succeeds_with_a_wrong_position(scene, method: str) -> None:
    """The safety property, whatever the failure status: no success without structure."""
    for _seed, _sc, est in collinear_estimates(scene, method, 0.0):
        assert not est.success and est.pose is None
        assert est.status in ("degenerate_scale", "no_consistent_hypothesis")


@pytest.mark.parametrize("method", ALL_METHODS)
def test_collinear_with_tracks_is_solved(scene, method: str) -> None:
    for seed, sc, est in collinear_estimates(scene, method, 1.0, structure="tracks"):
        assert est.success, f"seed {seed}: {est.status}: {est.message}"
        dc, dr = pose_errors(est.pose, sc.query_pose)
        assert dc < 0.1 and dr < 1.0
        assert est.num_inliers_3d >= 10


@pytest.mark.parametrize("method", ["2p1p", "2p2p"])
def test_collinear_with_reference_depth_is_solved(scene, method: str) -> None:
    sc = scene(0, noise_px=1.0, with_depth=True, **COLLINEAR)
    est = estimate_absolute_pose(
        sc.query_camera,
        sc.pairs,
        method,
        RansacOptions(max_iterations=100, min_iterations=100, structure="none"),
    )
    assert est.success, est.message
    assert pose_errors(est.pose, sc.query_pose)[0] < 0.1


def test_spread_scene_is_not_flagged(scene) -> None:
    """The degeneracy test must not reject the well-conditioned protocol scenes."""
    flagged = 0
    for seed in range(10):
        sc = scene(100 + seed, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.4)
        est = estimate_absolute_pose(
            sc.query_camera,
            sc.pairs,
            "2p1p",
            RansacOptions(max_iterations=100, min_iterations=100, structure="none", seed=seed),
        )
        flagged += est.status == "degenerate_scale"
        assert np.isfinite(est.position_std_m)
    assert flagged == 0
