"""Support beyond chance: are a pose's 2D-2D inliers more than random matches would give it?

A 2D-2D match is an inlier when the query keypoint lies within τ pixels of its epipolar line, a
band that covers a few percent of the image. Any pose therefore collects some inliers from
wrong matches, and among a few hundred matches RANSAC finds poses with 5-11 of them per map
image (``entry_p10`` queries against a ``fountain_p11`` map, which see another facade: a pose
14 m / 171° off on 23 inliers from two map images, position std 0.07 m). The checks on the
geometry of those inliers cannot tell: they are consistent with the pose by construction.

The test here is a-contrario (Moisan & Stival's contrario RANSAC, in its simplest form): the
expected number of inliers that *wrong* matches would give this very pose is measured by
re-pairing each map image's matches (each query keypoint with the map keypoint of a match whose
query keypoint is a neighbour in image row, see :func:`chance_inliers`): the same keypoints,
the same epipolar geometry, the associations destroyed. A map image supports the pose beyond chance when its inlier count is
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
    wrong: the mean inlier count over ``shifts`` re-pairings of the pair's matches.

    Each re-pairing gives the query keypoint of rank ``r`` (by image row) the map keypoint of the
    match of rank ``r + s``: a neighbour in height. Wrong matches of upright cameras keep the
    side of the horizon (the paper's outlier model projects the same point from another planar
    pose: a shuffle that ignores it saw 1.5-3 chance inliers where RANSAC found 20-35 on all-outlier
    scenes, and let 25 of 40 through; ranked neighbours see 5-13 and let 2 through).

    Args:
        problem: the query's matches; R: (3, 3), t: (3,) the pose; threshold_px: τ (pixels,
            Sampson error) that defines an inlier.
    """
    offsets, counts, n = problem.offsets, np.diff(problem.offsets), len(problem.xq)
    if n == 0:
        return np.zeros(len(counts))
    starts = np.repeat(offsets[:-1], counts)
    local = np.arange(n) - starts  # the pair blocks stay in place when sorted by (pair, row)
    size = np.repeat(np.maximum(counts, 1), counts)
    order = np.lexsort((problem.xq[:, 1], problem.pair))
    partners = np.empty((shifts, n), dtype=np.int64)
    for j in range(shifts):
        partners[j, order] = order[starts + (local + j + 1) % size]
    # All re-pairings in one compiled call: each is a copy of the problem's pairs.
    tiled = offsets[:-1][None, :] + n * np.arange(shifts)[:, None]
    all_offsets = np.append(tiled.ravel(), shifts * n)
    e2d, _ = errors_sq(np.ascontiguousarray(R, dtype=float), np.ascontiguousarray(t, dtype=float),
                       np.tile(problem.xq, (shifts, 1)), problem.xr[partners.ravel()], all_offsets,
                       problem.f_query, np.tile(problem.f_ref, (shifts, 1)), np.tile(problem.ref_R, (shifts, 1, 1)),
                       np.tile(problem.ref_t, (shifts, 1)), problem.xq3d[:0], problem.X3d[:0])
    inside = np.zeros(len(e2d) + 1)
    inside[1:] = np.cumsum(e2d <= threshold_px * threshold_px)
    per_pair = (inside[all_offsets[1:]] - inside[all_offsets[:-1]]).reshape(shifts, len(counts))
    return per_pair.mean(axis=0)


def beyond_chance(inlier_counts: np.ndarray, expected: np.ndarray, alpha: float = CHANCE_ALPHA) -> np.ndarray:
    """(P,) bool: which pairs' inlier counts (P,) are beyond chance, ``P(Poisson(expected) ≥ n) ≤ alpha``.

    A pair whose chance mean is zero (every re-paired match far from its line) needs one inlier."""
    n = np.asarray(inlier_counts, dtype=float)
    lam = np.maximum(np.asarray(expected, dtype=float), 1e-9)
    return (n > 0) & (pdtrc(np.maximum(n - 1, 0), lam) <= alpha)  # P(X > n - 1) = P(X ≥ n)
