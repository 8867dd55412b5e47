"""Support beyond chance: are a pose's 2D-2D inliers more than random matches would give it?

A 2D-2D match is an inlier when the query keypoint lies within τ pixels of its epipolar line, a
band that covers a few percent of the image. Any pose therefore collects some inliers from
wrong matches, and among a few hundred matches RANSAC finds poses with 5-11 of them per map
image (``entry_p10`` queries against a ``fountain_p11`` map, which see another facade: a pose
14 m / 171° off on 23 inliers from two map images, position std 0.07 m). The checks on the
geometry of those inliers cannot tell: they are consistent with the pose by construction.

The test here is a-contrario (Moisan & Stival's contrario RANSAC, in its simplest form): the
expected number of inliers that *random* matches would give this very pose is measured by
re-pairing each map image's matches (query keypoint ``i`` with the map keypoint of match
``i + s``, for a few cyclic shifts ``s``): the same keypoints, the same epipolar geometry, the
associations destroyed. A map image supports the pose beyond chance when its inlier count is
improbable under a Poisson law with that mean. Deterministic, and about ``CHANCE_SHIFTS × N``
Sampson errors: a fraction of the verification's time.
"""

from __future__ import annotations

import numpy as np
from scipy.special import pdtrc

from planarloc.robust.problem import AbsolutePoseProblem
from planarloc.robust.scoring import errors_sq

CHANCE_SHIFTS = 4
"""Re-pairings averaged for the expected chance inliers of a pair."""

CHANCE_ALPHA = 1e-4
"""A pair's inliers are beyond chance when a Poisson count with the chance mean reaches them
with probability at most this. RANSAC keeps the best of hundreds of hypotheses, so a single
hypothesis' 5 % is no evidence; real matches are far beyond it (KITTI map images: 45-1,000
inliers against 4-23 by chance, tail probabilities below 1e-29; the 14 m entry_p10 pose above:
1e-2.2 and 1e-2.0)."""


def chance_inliers(problem: AbsolutePoseProblem, R: np.ndarray, t: np.ndarray, threshold_px: float,
                   shifts: int = CHANCE_SHIFTS) -> np.ndarray:
    """(P,) expected 2D-2D inliers of each pair for ``cam_from_world = (R, t)`` if its matches were
    random: the mean inlier count over ``shifts`` cyclic re-pairings of the pair's matches.

    Args:
        problem: the query's matches; R: (3, 3), t: (3,) the pose; threshold_px: τ (pixels,
            Sampson error) that defines an inlier.
    """
    offsets = problem.offsets
    counts = np.diff(offsets)
    if len(problem.xq) == 0:
        return np.zeros(len(counts))
    starts = np.repeat(offsets[:-1], counts)
    local = np.arange(len(problem.xq)) - starts
    size = np.repeat(np.maximum(counts, 1), counts)
    R, t = np.ascontiguousarray(R, dtype=float), np.ascontiguousarray(t, dtype=float)
    no_points = problem.X3d[:0]
    total = np.zeros(len(counts))
    for j in range(1, shifts + 1):
        shift = np.repeat(np.maximum(1, (j * counts) // (shifts + 1)), counts)
        repaired = np.ascontiguousarray(problem.xr[starts + (local + shift) % size])
        e2d, _ = errors_sq(R, t, problem.xq, repaired, offsets, problem.f_query, problem.f_ref,
                           problem.ref_R, problem.ref_t, problem.xq3d[:0], no_points)
        inside = np.zeros(len(e2d) + 1)
        inside[1:] = np.cumsum(e2d <= threshold_px * threshold_px)
        total += inside[offsets[1:]] - inside[offsets[:-1]]
    return total / shifts


def beyond_chance(inlier_counts: np.ndarray, expected: np.ndarray, alpha: float = CHANCE_ALPHA) -> np.ndarray:
    """(P,) bool: which pairs' inlier counts (P,) are beyond chance, ``P(Poisson(expected) ≥ n) ≤ alpha``.

    A pair whose chance mean is zero (every re-paired match far from its line) needs one inlier."""
    n = np.asarray(inlier_counts, dtype=float)
    lam = np.maximum(np.asarray(expected, dtype=float), 1e-9)
    return (n > 0) & (pdtrc(np.maximum(n - 1, 0), lam) <= alpha)  # P(X > n - 1) = P(X ≥ n)
