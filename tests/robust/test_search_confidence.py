"""A search's own confidence (planarloc.robust.search_confidence): the chance that its samples
missed a pose of more support, exact against enumeration, and the estimate refusing the wrong
pose of a search stopped on a small budget, where the same scene with 100 samples succeeds."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from planarloc.geometry.pose import pose_errors
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions
from planarloc.robust.search_confidence import (
    MAX_MISS_PROBABILITY,
    inlier_ratios,
    missed_by_all,
    missed_by_draws,
    missed_by_pairs,
    pair_sample_chance,
)
from planarloc.synthetic.scenes import make_scene


def test_inlier_ratios_per_map_image_with_empty_images() -> None:
    offsets = np.array([0, 4, 4, 10, 10])
    inliers = np.array([1, 1, 0, 1, 0, 0, 1, 1, 1, 0], dtype=bool)
    ratios, counts = inlier_ratios(inliers, offsets)
    assert counts == [4, 0, 6, 0]
    np.testing.assert_allclose(ratios, [0.75, 0.0, 0.5, 0.0])
    ratios, counts = inlier_ratios(np.zeros(0, dtype=bool), np.array([0, 0, 0]))
    assert ratios == [0.0, 0.0] and counts == [0, 0]


def test_pair_sample_chance_weighs_images_by_matches_among_those_with_enough() -> None:
    ratios, counts = np.array([0.5, 0.8, 1.0]), np.array([30, 10, 1])
    # the third image has fewer than 2 matches: never drawn for a 2-match sample
    assert pair_sample_chance(ratios, counts, 2) == pytest.approx(0.75 * 0.25 + 0.25 * 0.64)
    assert pair_sample_chance(ratios, np.array([1, 1, 1]), 2) == 0.0


def test_missed_by_draws() -> None:
    assert missed_by_draws(0.2, 10) == pytest.approx(0.8**10)
    assert missed_by_draws(0.0, 100) == 1.0 and missed_by_draws(1.0, 1) == 0.0
    assert missed_by_draws(0.3, 0) == 1.0


@pytest.mark.parametrize("ratios", [[0.5, 0.6, 0.7], [0.9, 0.1, 0.4, 0.6], [0.3, 0.3]])
def test_missed_by_pairs_matches_enumeration(ratios: list[float]) -> None:
    """1 - P(at least two images had an all-inlier sample), against the sum over every outcome."""
    r, m, n = np.array(ratios), 5, 12
    counts = np.full(len(r), 40)
    good = 1.0 - (1.0 - r**m) ** n
    expected = 0.0
    for outcome in itertools.product([False, True], repeat=len(r)):
        if sum(outcome) < 2:
            expected += float(np.prod([g if o else 1.0 - g for g, o in zip(good, outcome)]))
    assert missed_by_pairs(r, counts, m, n) == pytest.approx(expected, rel=1e-12)
    # an image with fewer than m matches never has a sample
    counts[0] = m - 1
    assert missed_by_pairs(r, counts, m, n) >= expected


def test_the_product_over_searches_stops_once_it_is_below_the_limit() -> None:
    calls = []

    def search(p: float):
        return lambda: calls.append(p) or p

    assert missed_by_all([search(0.5), search(0.5), search(0.3)]) == pytest.approx(0.075)
    assert calls == [0.5, 0.5, 0.3]
    calls.clear()
    assert missed_by_all([search(0.5), search(0.01), search(0.3)]) == pytest.approx(0.005)
    assert calls == [0.5, 0.01]  # the third search is not evaluated
    assert missed_by_all([]) == 1.0


def test_more_samples_and_more_support_miss_less() -> None:
    counts = np.array([50, 50, 50])
    low, high = np.array([0.3, 0.3, 0.3]), np.array([0.6, 0.6, 0.6])
    for missed in (
        lambda r, n: missed_by_draws(pair_sample_chance(r, counts, 2), n),
        lambda r, n: missed_by_pairs(r, counts, 5, n),
    ):
        assert missed(low, 10) > missed(low, 100) > 0.0
        assert missed(low, 10) > missed(high, 10)


def _hard_scene(cell: tuple[int, int, int, int], outliers: float, matches: int):
    """A scene of benchmarks/robustness.py's hard protocol (seed, cell and trial as it draws them)
    and its RANSAC seed."""
    ss = np.random.SeedSequence(list(cell))
    scene = make_scene(
        np.random.default_rng(ss), num_refs=3, matches_per_pair=matches, noise_px=1.5, outlier_ratio=outliers
    )
    return scene, int(ss.generate_state(1)[0])


@pytest.mark.parametrize(
    ("cell", "outliers", "matches"),
    [((70, 0, 4, 24), 0.6, 50), ((70, 0, 3, 45), 0.5, 50), ((70, 1, 3, 58), 0.5, 20)],
)
def test_a_search_stopped_early_does_not_vouch_for_its_wrong_pose(
    cell, outliers: float, matches: int
) -> None:
    """10 samples: the best pose found is 2.2-2.5 m off, and every other check passes it (it was a
    success with a std of 0.09-0.23 m before this check); 100 samples on the same scene find the
    right basin, and nothing is refused for want of samples."""
    scene, seed = _hard_scene(cell, outliers, matches)

    def estimate(samples: int):
        options = RansacOptions(
            max_iterations=samples, min_iterations=samples, seed=seed, structure="none", cross_check=False
        )
        return estimate_absolute_pose(scene.query_camera, scene.pairs, "2p1p", options)

    short = estimate(10)
    assert short.status == "search_incomplete", short.status
    assert "max_iterations" in short.message and f"> {MAX_MISS_PROBABILITY}" in short.message
    assert short.pose is None and short.unreliable_pose is not None
    assert pose_errors(short.unreliable_pose, scene.query_pose)[0] > 1.0
    full = estimate(100)
    assert full.status != "search_incomplete"
    pose = full.pose if full.success else full.unreliable_pose
    assert pose is not None and pose_errors(pose, scene.query_pose)[0] < 0.1
