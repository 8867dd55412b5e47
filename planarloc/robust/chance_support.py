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
the same epipolar geometry, the associations destroyed. A map image supports the pose beyond chance when its
inlier count is improbable under a Poisson law with that mean. Deterministic, and ``CHANCE_SHIFTS × N``
Sampson errors in one compiled call.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.special import pdtrc

from planarloc.geometry.epipolar_kernels import relative_essential_into, sampson_sq
from planarloc.robust.problem import AbsolutePoseProblem, ProblemArrays

CHANCE_SHIFTS = 4
"""Re-pairings averaged for the expected chance inliers of a pair."""

CHANCE_ALPHA = 1e-4
"""A pair's inliers are beyond chance when a Poisson count with the chance mean reaches them
with probability at most this. RANSAC keeps the best of hundreds of hypotheses, so a single
hypothesis' 5 % is no evidence; real matches are far beyond it (KITTI map images: 45-1,000
inliers against 4-23 by chance, tail probabilities below 1e-29; the 14 m entry_p10 pose above:
1e-2.2 and 1e-2.0)."""


def chance_inliers(
    problem: AbsolutePoseProblem,
    R: np.ndarray,
    t: np.ndarray,
    threshold_px: float,
    shifts: int = CHANCE_SHIFTS,
) -> np.ndarray:
    """(P,) expected 2D-2D inliers of each pair for ``cam_from_world = (R, t)`` if its matches were
    wrong: the mean inlier count over ``shifts`` re-pairings of the pair's matches.

    Each re-pairing gives the query keypoint of rank ``r`` (by image row) the map keypoint of the
    match of rank ``r + s`` (cyclic within the pair), ``s = 1 … shifts``: a neighbour in height.
    Wrong matches of upright cameras keep the side of the horizon (the paper's outlier model
    projects the same point from another planar pose: a shuffle that ignores it saw 1.5-3 chance
    inliers where RANSAC found 20-35 on all-outlier scenes, and let 25 of 40 through; ranked
    neighbours see 5-13 and let 2 through).

    Args:
        problem: the query's matches; R: (3, 3), t: (3,) the pose; threshold_px: τ (pixels,
            Sampson error) that defines an inlier.
    """
    if len(problem.xq) == 0:
        return np.zeros(problem.num_pairs)
    order = np.lexsort((problem.xq[:, 1], problem.pair))  # pair blocks stay in place
    return _chance_kernel(
        np.ascontiguousarray(R, dtype=float),
        np.ascontiguousarray(t, dtype=float),
        problem.arrays,
        order,
        float(threshold_px) ** 2,
        int(shifts),
    )


@njit(cache=True, error_model="numpy")
def _chance_kernel(
    R: np.ndarray,
    t: np.ndarray,
    prob: ProblemArrays,
    order: np.ndarray,
    threshold_sq: float,
    shifts: int,
) -> np.ndarray:
    # Compiled: numpy's per-call overhead for a few dozen matches was ~8 % of a query's time.
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    ref_R, ref_t = prob.ref_R, prob.ref_t
    out = np.zeros(offsets.shape[0] - 1)
    E = np.empty((3, 3))
    for p in range(offsets.shape[0] - 1):
        lo, m = offsets[p], offsets[p + 1] - offsets[p]
        if m < 2:
            continue
        relative_essential_into(ref_R[p], ref_t[p], R, t, E)
        hits = 0
        for r in range(m):
            i = order[lo + r]
            for s in range(1, shifts + 1):
                k = order[lo + (r + s) % m]
                if (
                    sampson_sq(E, xq[i], xr[k], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
                    <= threshold_sq
                ):
                    hits += 1
        out[p] = hits / shifts
    return out


def beyond_chance(inlier_counts: np.ndarray, expected: np.ndarray, alpha: float = CHANCE_ALPHA) -> np.ndarray:
    """(P,) bool: which pairs' inlier counts (P,) are beyond chance, ``P(Poisson(expected) ≥ n) ≤ alpha``.

    A pair whose chance mean is zero (every re-paired match far from its line) needs one inlier."""
    n = np.asarray(inlier_counts, dtype=float)
    lam = np.maximum(np.asarray(expected, dtype=float), 1e-9)
    return (n > 0) & (pdtrc(np.maximum(n - 1, 0), lam) <= alpha)  # P(X > n - 1) = P(X ≥ n)
