"""MSAC scoring of absolute-pose hypotheses over every match of every pair (numba).

A hypothesis ``query_from_world = (R_q, t_q)`` implies for pair ``p`` the relative pose
``p_from_query = (R_p R_qᵀ, t_p - R_p R_qᵀ t_q)`` and the essential matrix ``E_p``; each
2D-2D match is scored by its Sampson error in pixels under ``E_p`` and each 2D-3D
constraint by its reprojection error in pixels. The authors' code counts inliers with the
algebraic error ``|x_iᵀ E x_j|``, which is not in pixels and depends on the scale of E.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry.epipolar_kernels import (
    essential_into,
    relative_essential_into,
    reprojection_sq,
    sampson_sq,
)
from planarloc.robust.problem import ProblemArrays


@njit(cache=True, inline="always")
def msac_add(cost: float, inliers: int, e: float, threshold_sq: float) -> tuple[float, int]:
    """One datum of an MSAC sum: ``cost + min(e, τ²)``, and ``inliers + 1`` if ``e < τ²``."""
    if e < threshold_sq:
        return cost + e, inliers + 1
    return cost + threshold_sq, inliers


@njit(cache=True, error_model="numpy")
def errors_sq(Rq: np.ndarray, tq: np.ndarray, prob: ProblemArrays) -> tuple[np.ndarray, np.ndarray]:
    """Squared pixel errors of one hypothesis ``query_from_world = (Rq (3, 3), tq (3,))`` on the
    problem ``prob``: (N,) Sampson and (M,) reprojection (scaled by ``f_query[2:]``, see
    :class:`planarloc.robust.problem.AbsolutePoseProblem`)."""
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    ref_R, ref_t, xq3d, X3d = prob.ref_R, prob.ref_t, prob.xq3d, prob.X3d
    n = xq.shape[0]
    e2d = np.empty(n)
    E = np.empty((3, 3))
    for p in range(offsets.shape[0] - 1):
        relative_essential_into(ref_R[p], ref_t[p], Rq, tq, E)
        for i in range(offsets[p], offsets[p + 1]):
            e2d[i] = sampson_sq(E, xq[i], xr[i], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
    e3d = np.empty(X3d.shape[0])
    for i in range(X3d.shape[0]):
        e3d[i] = reprojection_sq(Rq, tq, X3d[i], xq3d[i], f_query[2], f_query[3])
    return e2d, e3d


@njit(cache=True, error_model="numpy")
def msac_scores(
    Rs: np.ndarray,
    ts: np.ndarray,
    num: int,
    prob: ProblemArrays,
    threshold_sq: float,
    bound: float = np.inf,
) -> tuple[np.ndarray, np.ndarray]:
    """MSAC cost ``Σ min(e², τ²)`` and inlier count of the first ``num`` hypotheses.

    Args:
        Rs, ts: (H, 3, 3), (H, 3) hypotheses ``query_from_world``.
        prob: the problem's arrays (matches, focal lengths, reference poses, 2D-3D constraints).
        threshold_sq: τ² in pixels².
        bound: cost of the best model so far. Scoring of a hypothesis stops (after a pair)
            once its partial cost exceeds the best cost seen, so most bad hypotheses cost a
            fraction of a full pass; their returned cost is then only a lower bound (and their
            inlier count partial), which leaves the argmin exact.

    Returns:
        cost (num,), inliers (num,).
    """
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    ref_R, ref_t, xq3d, X3d = prob.ref_R, prob.ref_t, prob.xq3d, prob.X3d
    cost = np.empty(num)
    inl = np.zeros(num, dtype=np.int64)
    E = np.empty((3, 3))
    best = bound
    for h in range(num):
        c = 0.0
        k = 0
        Rq = Rs[h]
        tq = ts[h]
        for p in range(offsets.shape[0] - 1):
            relative_essential_into(ref_R[p], ref_t[p], Rq, tq, E)
            for i in range(offsets[p], offsets[p + 1]):
                e = sampson_sq(E, xq[i], xr[i], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
                c, k = msac_add(c, k, e, threshold_sq)
            if c > best:
                break
        if c > best:
            cost[h] = c
            inl[h] = k
            continue
        for i in range(X3d.shape[0]):
            e = reprojection_sq(Rq, tq, X3d[i], xq3d[i], f_query[2], f_query[3])
            c, k = msac_add(c, k, e, threshold_sq)
        cost[h] = c
        inl[h] = k
        if c < best:
            best = c
    return cost, inl


@njit(cache=True, error_model="numpy")
def relative_msac_scores(
    R: np.ndarray,
    t: np.ndarray,
    valid: np.ndarray,
    sample_pair: np.ndarray,
    prob: ProblemArrays,
    threshold_sq: float,
) -> np.ndarray:
    """MSAC cost of relative-pose candidates ``ref_from_query`` over the matches of their own pair.

    Args:
        R, t, valid: (S, A, 3, 3), (S, A, 3), (S, A) candidates of S samples.
        sample_pair: (S,) pair of each sample.

    Returns:
        (S, A) costs, inf where not valid.
    """
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    S, A = valid.shape
    cost = np.full((S, A), np.inf)
    E = np.empty((3, 3))
    for s in range(S):
        p = sample_pair[s]
        for a in range(A):
            if not valid[s, a]:
                continue
            essential_into(R[s, a], t[s, a], E)
            c = 0.0
            for i in range(offsets[p], offsets[p + 1]):
                e = sampson_sq(E, xq[i], xr[i], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
                c += e if e < threshold_sq else threshold_sq
            cost[s, a] = c
    return cost
