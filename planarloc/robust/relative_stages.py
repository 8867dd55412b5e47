"""The two stages of the relative-pose families (2p2p and the 5p5p / 8p8p baselines) around their
solver, in two compiled calls (numba).

Paper Sec. IV-B: stage 1 draws minimal samples within each map image and keeps, per image, the
best distinct relative poses of its solver; stage 2 combines the kept poses of every two images
into absolute hypotheses (Rcheck, triangulation, Pdcheck, consistency). The solver itself stays
a Python call between the two (each family has its own batch kernel, and a kernel that takes
another as an argument is not kept in numba's cache). The kernels called here are those the
stages ran one by one from Python before, so the hypotheses are the same to the bit; the ~40
numpy calls between them cost ~0.1 ms on every short 6DoF check of a planar pose, more than half
as much again as the kernels other than the solver (benchmarks/estimator_profile.py, issue 31).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.robust.hypotheses import (
    Hypotheses,
    RelativePoses,
    hypotheses_from_relative_poses,
    top_distinct_relative,
)
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.sampling import draw_within_pairs
from planarloc.robust.scoring import relative_msac_scores


@njit(cache=True)
def relative_samples(
    u: np.ndarray, prob: ProblemArrays, eligible: np.ndarray, n: int, m: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage 1's samples: ``n`` samples of ``m`` distinct matches in each map image of
    ``eligible`` (E,), in that order.

    Args:
        u: (E·n, m) uniform variates (:func:`~planarloc.robust.sampling.draw_within_pairs`).
        prob: the problem's arrays.

    Returns:
        sample_pair (E·n,) the map image of each sample, and its rays xq, xr (E·n, m, 3).
    """
    S = eligible.shape[0] * n
    sample_pair = np.empty(S, dtype=np.int64)
    for e in range(eligible.shape[0]):
        for s in range(n):
            sample_pair[e * n + s] = eligible[e]
    samples = np.empty((S, m), dtype=np.int64)
    draw_within_pairs(u, prob.offsets, sample_pair, m, samples)
    xq = np.empty((S, m, 3))
    xr = np.empty((S, m, 3))
    for s in range(S):
        for a in range(m):
            i = samples[s, a]
            for c in range(3):
                xq[s, a, c] = prob.xq[i, c]
                xr[s, a, c] = prob.xr[i, c]
    return sample_pair, xq, xr


@njit(cache=True)
def _kept_poses(pairs: np.ndarray, count: np.ndarray, top_R: np.ndarray, top_t: np.ndarray) -> RelativePoses:
    """The poses stage 1 kept for the map images ``pairs`` (C,): (C, K) from top_R (P, K, 3, 3),
    top_t (P, K, 3), valid where within ``count`` (P,)."""
    C, K = pairs.shape[0], top_R.shape[1]
    R = np.empty((C, K, 3, 3))
    t = np.empty((C, K, 3))
    valid = np.empty((C, K), dtype=np.bool_)
    for c in range(C):
        p = pairs[c]
        for a in range(K):
            valid[c, a] = a < count[p]
            for i in range(3):
                t[c, a, i] = top_t[p, a, i]
                for j in range(3):
                    R[c, a, i, j] = top_R[p, a, i, j]
    return RelativePoses(R, t, valid)


@njit(cache=True, error_model="numpy")
def hypotheses_of_relative_samples(
    rel: RelativePoses,
    sample_pair: np.ndarray,
    eligible: np.ndarray,
    n: int,
    prob: ProblemArrays,
    threshold_sq: float,
    top_k: int,
    pair_j: np.ndarray,
    pair_k: np.ndarray,
    cos_rcheck: float,
    cos_consistency: float,
    counters: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The end of stage 1 and stage 2: each sample's relative poses scored on its own map image
    (:func:`~planarloc.robust.scoring.relative_msac_scores`), the ``top_k`` best distinct ones
    kept per image (:func:`~planarloc.robust.hypotheses.top_distinct_relative`), then combined
    for every two images that kept some (:func:`~planarloc.robust.hypotheses.hypotheses_from_relative_poses`).

    Args:
        rel: the solver's output for the samples of :func:`relative_samples` (S, A).
        sample_pair, eligible, n: as :func:`relative_samples` drew them.
        threshold_sq: τ² (pixels²).
        pair_j, pair_k: (C,) every two map images, j < k.
        cos_rcheck, cos_consistency: cosines of ``e_th`` and ``α_th``.
        counters: (5,) the hypothesis counters, incremented.

    Returns:
        ``query_from_world`` hypotheses R (H, 3, 3), t (H, 3).
    """
    cost = relative_msac_scores(rel.R, rel.t, rel.valid, sample_pair, prob, threshold_sq)
    P = prob.offsets.shape[0] - 1
    top_R = np.zeros((P, top_k, 3, 3))
    top_t = np.zeros((P, top_k, 3))
    count = np.zeros(P, dtype=np.int64)
    top_distinct_relative(rel.R, rel.t, cost, eligible, n, top_k, top_R, top_t, count)
    C = 0
    for c in range(pair_j.shape[0]):
        if count[pair_j[c]] > 0 and count[pair_k[c]] > 0:
            C += 1
    pj = np.empty(C, dtype=np.int64)
    pk = np.empty(C, dtype=np.int64)
    C = 0
    for c in range(pair_j.shape[0]):
        if count[pair_j[c]] > 0 and count[pair_k[c]] > 0:
            pj[C], pk[C] = pair_j[c], pair_k[c]
            C += 1
    rel_j = _kept_poses(pj, count, top_R, top_t)
    rel_k = _kept_poses(pk, count, top_R, top_t)
    found = Hypotheses(np.empty((C * top_k * top_k, 3, 3)), np.empty((C * top_k * top_k, 3)), counters)
    cnt = hypotheses_from_relative_poses(
        rel_j, rel_k, pj, pk, prob.ref_R, prob.ref_t, cos_rcheck, cos_consistency, found
    )
    return found.R[:cnt], found.t[:cnt]
