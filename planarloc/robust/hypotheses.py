"""Absolute-pose hypotheses from minimal samples, with the paper's multiple checking (numba).

Counters (indices into the ``counters`` array): 0 hypotheses, 1 rejected by Rcheck (eq. 12),
2 rejected by Pdcheck (ρ ≤ 0 or a negative depth), 3 rejected by the consistency check,
4 degenerate (no finite solution).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.epipolar_kernels import sampson_sq
from planarloc.solvers.abspose_2p1p import scale_2p1p, scale_from_point3d
from planarloc.solvers.abspose_2p2p import triangulate_scales
from planarloc.solvers.abspose_p3p import MAX_SOLUTIONS as P3P_MAX_SOLUTIONS
from planarloc.solvers.abspose_p3p import solve_p3p
from planarloc.solvers.abspose_up2p import solve_up2p
from planarloc.solvers.relpose_planar_2p import planar_pose_into, solve_planar_2p

HYPOTHESES, RCHECK, PDCHECK, CONSISTENCY, DEGENERATE = range(5)


@njit(cache=True, error_model="numpy", inline="always")
def _positive_depths(R: np.ndarray, t: np.ndarray, xq: np.ndarray, xr: np.ndarray) -> bool:
    """Both midpoint depths of ``x_r λr ≈ λq R x_q + t`` positive."""
    a0 = R[0, 0] * xq[0] + R[0, 1] * xq[1] + R[0, 2] * xq[2]
    a1 = R[1, 0] * xq[0] + R[1, 1] * xq[1] + R[1, 2] * xq[2]
    a2 = R[2, 0] * xq[0] + R[2, 1] * xq[1] + R[2, 2] * xq[2]
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = xr[0] * xr[0] + xr[1] * xr[1] + xr[2] * xr[2]
    ab = a0 * xr[0] + a1 * xr[1] + a2 * xr[2]
    at = a0 * t[0] + a1 * t[1] + a2 * t[2]
    bt = xr[0] * t[0] + xr[1] * t[1] + xr[2] * t[2]
    det = aa * bb - ab * ab
    if det <= 1e-12 * aa * bb:
        return False
    return (-at * bb + ab * bt) / det > 0 and (aa * bt - ab * at) / det > 0


@njit(cache=True, error_model="numpy", inline="always")
def _emit_planar(
    rho: float,
    in_front: bool,
    R: np.ndarray,
    tt: np.ndarray,
    Rj: np.ndarray,
    tj: np.ndarray,
    out_R: np.ndarray,
    out_t: np.ndarray,
    out: int,
    counters: np.ndarray,
) -> int:
    """Pdcheck of a scaled planar relative pose, then its ``query_from_world`` at ``out``.

    ``j_from_query = (R, ρ t̃)`` with reference ``j_from_world = (Rj, tj)`` gives
    ``query_from_world = (Rᵀ Rj, Rᵀ (tj − ρ t̃))``. Rejected (counted as Pdcheck) unless ρ > 0
    and ``in_front`` (the caller's cheirality test).

    Returns:
        the next free output row.
    """
    if not (rho > 0.0 and in_front):
        counters[PDCHECK] += 1
        return out
    out_R[out] = m3.t_mul(R, Rj)
    out_t[out] = m3.t_vec(R, tj - rho * tt)
    return out + 1


@njit(cache=True, error_model="numpy")
def hypotheses_2p1p(
    samples: np.ndarray,
    third_is_3d: np.ndarray,
    pj: np.ndarray,
    pk: np.ndarray,
    xq: np.ndarray,
    xr: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    xq3d: np.ndarray,
    X3d: np.ndarray,
    out_R: np.ndarray,
    out_t: np.ndarray,
    counters: np.ndarray,
) -> int:
    """2p1p hypotheses (paper Sec. IV-C) with Pdcheck.

    Args:
        samples: (S, 3) rows ``(i1, i2, i3)``: two matches of pair ``pj`` and the third, a
            match row of pair ``pk`` or, where ``third_is_3d``, a row of ``xq3d``/``X3d``
            (structure mode: scale from a 2D-3D constraint, same unknown ρ).
        out_R, out_t: (2S, 3, 3), (2S, 3) output buffers for ``query_from_world``.
        counters: (5,) int64, incremented.

    Returns:
        number of hypotheses written.
    """
    sq = np.empty((2, 3))
    sr = np.empty((2, 3))
    thetas = np.empty(2)
    phis = np.empty(2)
    R = np.zeros((3, 3))
    R[1, 1] = 1.0
    tt = np.empty(3)
    out = 0
    for s in range(samples.shape[0]):
        i1, i2, i3 = samples[s, 0], samples[s, 1], samples[s, 2]
        sq[0], sq[1] = xq[i1], xq[i2]
        sr[0], sr[1] = xr[i1], xr[i2]
        n = solve_planar_2p(sq, sr, thetas, phis)
        if n == 0:
            counters[DEGENERATE] += 1
            continue
        j = pj[s]
        Rj, tj = ref_R[j], ref_t[j]
        for m in range(n):
            counters[HYPOTHESES] += 1
            c, sn = np.cos(thetas[m]), np.sin(thetas[m])
            R[0, 0], R[0, 2], R[2, 0], R[2, 2] = c, -sn, sn, c
            sp, cp = np.sin(phis[m]), np.cos(phis[m])
            tt[0] = -(c * sp - sn * cp)
            tt[1] = 0.0
            tt[2] = -(sn * sp + c * cp)
            if third_is_3d[s]:
                Xref = m3.vec(Rj, X3d[i3]) + tj
                v = m3.vec(R, xq3d[i3])
                rho = scale_from_point3d(tt, Xref, v)
                in_front = rho > 0 and m3.t_vec(R, Xref - rho * tt)[2] > 0
            else:
                k = pk[s]
                R21 = m3.mul_t(ref_R[k], Rj)
                t21 = ref_t[k] - m3.vec(R21, tj)
                a = m3.vec(R21, tt)
                y = m3.vec(R21, m3.vec(R, xq[i3]))
                rho = scale_2p1p(a, t21, y, xr[i3])
                in_front = rho > 0 and _positive_depths(m3.mul(R21, R), rho * a + t21, xq[i3], xr[i3])
            if rho != rho:
                counters[DEGENERATE] += 1
                continue
            out = _emit_planar(rho, in_front, R, tt, Rj, tj, out_R, out_t, out, counters)
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_from_relative_poses(
    Ra: np.ndarray,
    ta: np.ndarray,
    va: np.ndarray,
    Rb: np.ndarray,
    tb: np.ndarray,
    vb: np.ndarray,
    pj: np.ndarray,
    pk: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    cos_rcheck: float,
    cos_consistency: float,
    out_R: np.ndarray,
    out_t: np.ndarray,
    counters: np.ndarray,
) -> int:
    """Absolute hypotheses from relative poses to two references (2p2p and the baselines).

    Paper Sec. IV-B: Rcheck (eq. 12), triangulation (eq. 13-15) and Pdcheck, consistency.

    Args:
        Ra, ta, va: (S, A, 3, 3), (S, A, 3), (S, A) candidate ``j_from_query`` per sample
            (unit ``t``), valid flags; Rb, tb, vb likewise for ``k_from_query``.
        pj, pk: (S,) the two pairs of each sample.
        cos_rcheck, cos_consistency: cosines of ``e_th`` and ``α_th``.

    Returns:
        number of ``query_from_world`` hypotheses written to out_R, out_t.
    """
    out = 0
    for s in range(Ra.shape[0]):
        j, k = pj[s], pk[s]
        Rj, tj, Rk, tk = ref_R[j], ref_t[j], ref_R[k], ref_t[k]
        R12 = m3.mul_t(Rj, Rk)  # j_from_k, eq. (12)
        t12 = tj - m3.vec(R12, tk)
        any_valid = False
        for a in range(Ra.shape[1]):
            if not va[s, a]:
                continue
            for b in range(Rb.shape[1]):
                if not vb[s, b]:
                    continue
                any_valid = True
                counters[HYPOTHESES] += 1
                Rab = m3.mul_t(Ra[s, a], Rb[s, b])
                cos_e = 0.5 * (np.sum(R12 * Rab) - 1.0)  # tr(R12 Rabᵀ) = Σ R12 ∘ Rab
                if cos_e < cos_rcheck:
                    counters[RCHECK] += 1
                    continue
                t2_in_1 = m3.vec(Rab, tb[s, b])
                rho, rho2, reg = triangulate_scales(ta[s, a], t2_in_1, t12)
                if reg:
                    counters[DEGENERATE] += 1
                    continue
                if rho <= 0 or rho2 <= 0:
                    counters[PDCHECK] += 1
                    continue
                Rq = m3.t_mul(Ra[s, a], Rj)
                tq = m3.t_vec(Ra[s, a], tj - rho * ta[s, a])
                cq = -m3.t_vec(Rq, tq)
                that = m3.vec(Rk, cq) + tk  # query centre seen from k; must point along t̃₂
                nt = np.sqrt(np.sum(that * that))
                if nt < 1e-12 or np.sum(that * tb[s, b]) / nt < cos_consistency:
                    counters[CONSISTENCY] += 1
                    continue
                out_R[out] = Rq
                out_t[out] = tq
                out += 1
        if not any_valid:
            counters[DEGENERATE] += 1
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_up2p(
    samples: np.ndarray,
    pj: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    xq3d: np.ndarray,
    X3d: np.ndarray,
    out_R: np.ndarray,
    out_t: np.ndarray,
    counters: np.ndarray,
) -> int:
    """Upright P2P hypotheses (structure mode): two 2D-3D constraints, yaw relative to pair ``pj``.

    Args:
        samples: (S, 2) rows of ``xq3d`` / ``X3d``.
        pj: (S,) the reference whose frame is upright relative to the query (local planar motion).
        out_R, out_t: (2S, 3, 3), (2S, 3) ``query_from_world`` outputs.
    """
    x = np.empty((2, 3))
    X = np.empty((2, 3))
    th = np.empty(2)
    ts = np.empty((2, 3))
    R = np.zeros((3, 3))
    R[1, 1] = 1.0
    out = 0
    for s in range(samples.shape[0]):
        j = pj[s]
        Rj, tj = ref_R[j], ref_t[j]
        for k in range(2):
            x[k] = xq3d[samples[s, k]]
            X[k] = m3.vec(Rj, X3d[samples[s, k]]) + tj
        n = solve_up2p(x, X, th, ts)
        if n == 0:
            counters[DEGENERATE] += 1
            continue
        for m in range(n):
            counters[HYPOTHESES] += 1
            c, sn = np.cos(th[m]), np.sin(th[m])
            R[0, 0], R[0, 2], R[2, 0], R[2, 2] = c, -sn, sn, c
            out_R[out] = m3.mul(R, Rj)
            out_t[out] = m3.vec(R, tj) + ts[m]
            out += 1
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_p3p(
    samples: np.ndarray,
    xq3d: np.ndarray,
    X3d: np.ndarray,
    out_R: np.ndarray,
    out_t: np.ndarray,
    counters: np.ndarray,
) -> int:
    """6DoF P3P hypotheses from three 2D-3D constraints (:mod:`planarloc.solvers.abspose_p3p`).

    Args:
        samples: (S, 3) rows of ``xq3d`` / ``X3d``.
        out_R, out_t: (4S, 3, 3), (4S, 3) ``query_from_world`` outputs.

    Returns:
        number of hypotheses written.
    """
    Rs = np.empty((P3P_MAX_SOLUTIONS, 3, 3))
    ts = np.empty((P3P_MAX_SOLUTIONS, 3))
    out = 0
    for s in range(samples.shape[0]):
        n = solve_p3p(xq3d[samples[s]], X3d[samples[s]], Rs, ts)
        if n == 0:
            counters[DEGENERATE] += 1
            continue
        counters[HYPOTHESES] += n
        for k in range(n):  # element loops: a 3-D slice assignment compiles numba's shape-error formatting
            for a in range(3):
                out_t[out + k, a] = ts[k, a]
                for b in range(3):
                    out_R[out + k, a, b] = Rs[k, a, b]
        out += n
    return out


@njit(cache=True, error_model="numpy")
def top_distinct_relative(
    R: np.ndarray,
    t: np.ndarray,
    cost: np.ndarray,
    eligible: np.ndarray,
    n: int,
    top_k: int,
    out_R: np.ndarray,
    out_t: np.ndarray,
    out_count: np.ndarray,
) -> None:
    """Stage 1 of the relative-pose families: per pair, the ``top_k`` cheapest distinct relative poses.

    Args:
        R, t: (S, A, 3, 3), (S, A, 3) candidates of S = len(eligible)·n samples, ``n`` per pair
            in the order of ``eligible`` (the solver's outputs, A per sample).
        cost: (S, A) their MSAC cost over their own pair (inf where not valid).
        eligible: (E,) the pairs that were sampled.
        out_R, out_t: (P, top_k, 3, 3), (P, top_k, 3) outputs; out_count (P,) how many per pair.

    Two candidates are the same pose (found by two samples) when their rotations agree to
    ``tr(R_a R_bᵀ) > 3 − 1e-4`` and their unit translations to a cosine above 0.9998.
    """
    A = R.shape[1]
    out_count[:] = 0
    for e in range(eligible.shape[0]):
        pair = eligible[e]
        c = cost[e * n : (e + 1) * n].ravel()
        order = np.argsort(c)
        k = 0
        for o in order:
            if not np.isfinite(c[o]) or k == top_k:
                break
            s_, a_ = e * n + o // A, o % A
            same = False
            for q in range(k):
                if (
                    np.sum(R[s_, a_] * out_R[pair, q]) > 3.0 - 1e-4
                    and m3.dot(t[s_, a_], out_t[pair, q]) > 0.9998
                ):
                    same = True
                    break
            if same:
                continue
            out_R[pair, k] = R[s_, a_]
            out_t[pair, k] = t[s_, a_]
            k += 1
        out_count[pair] = k


@njit(cache=True, error_model="numpy")
def planar_relative_candidates(
    samples: np.ndarray,
    sample_pair: np.ndarray,
    xq: np.ndarray,
    xr: np.ndarray,
    offsets: np.ndarray,
    f_query: np.ndarray,
    f_ref: np.ndarray,
    threshold_sq: float,
    top_k: int,
    max_scored: int,
    out_R: np.ndarray,
    out_t: np.ndarray,
    out_pair: np.ndarray,
    counters: np.ndarray,
) -> int:
    """Stage 1 of the consensus 2p1p: per pair, the ``top_k`` best distinct planar relative poses.

    Every sample's planar 2p solutions (paper Sec. IV-A) are scored by MSAC over the matches of
    their own pair; per pair the ``top_k`` cheapest that differ from each other (in rotation
    or translation direction) are kept.

    Args:
        samples: (S, 2) match rows, both of pair ``sample_pair[s]``.
        threshold_sq: MSAC threshold τ² (pixels²).
        max_scored: a pair with more matches is scored on every s-th (s = ⌈n / max_scored⌉);
            ranking relative poses needs no more.
        out_R, out_t, out_pair: (P * top_k, ...) outputs: ``ref_from_query`` rotation, unit
            translation, pair index.

    Returns:
        number of relative poses written.
    """
    S = samples.shape[0]
    thetas = np.empty((S, 2))
    phis = np.empty((S, 2))
    cost = np.full(2 * S, np.inf)
    P = offsets.shape[0] - 1
    # Per pair, the top_k smallest costs so far (ascending): a candidate whose partial cost
    # exceeds the last cannot be kept, so its scoring stops early (most samples hold an outlier).
    bound = np.full((P, top_k), np.inf)
    sq = np.empty((2, 3))
    sr = np.empty((2, 3))
    E = np.empty((3, 3))
    for s in range(S):
        sq[0], sq[1] = xq[samples[s, 0]], xq[samples[s, 1]]
        sr[0], sr[1] = xr[samples[s, 0]], xr[samples[s, 1]]
        n = solve_planar_2p(sq, sr, thetas[s], phis[s])
        if n == 0:
            counters[DEGENERATE] += 1
        p = sample_pair[s]
        for m in range(n):  # relative poses are not counted as hypotheses; stage 2 counts those
            c, sn = np.cos(thetas[s, m]), np.sin(thetas[s, m])
            sp, cp = np.sin(phis[s, m]), np.cos(phis[s, m])
            t0 = -(c * sp - sn * cp)
            t2 = -(sn * sp + c * cp)
            # E = [t]x R with R = [[c, 0, -s], [0, 1, 0], [s, 0, c]], t = (t0, 0, t2)
            E[0, 0], E[0, 1], E[0, 2] = 0.0, -t2, 0.0
            E[1, 0], E[1, 1], E[1, 2] = t2 * c - t0 * sn, 0.0, -t2 * sn - t0 * c
            E[2, 0], E[2, 1], E[2, 2] = 0.0, t0, 0.0
            acc = 0.0
            worst = bound[p, top_k - 1]
            n_p = offsets[p + 1] - offsets[p]
            for i in range(offsets[p], offsets[p + 1], max(1, (n_p + max_scored - 1) // max_scored)):
                e = sampson_sq(E, xq[i], xr[i], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
                acc += e if e < threshold_sq else threshold_sq
                if acc > worst:
                    break
            if acc > worst:
                continue
            cost[2 * s + m] = acc
            q = top_k - 1
            while q > 0 and bound[p, q - 1] > acc:
                bound[p, q] = bound[p, q - 1]
                q -= 1
            bound[p, q] = acc
    order = np.argsort(cost)
    out = 0
    kept = np.zeros(P, dtype=np.int64)
    for o in order:
        if not cost[o] < np.inf:
            break
        s, m = o // 2, o % 2
        p = sample_pair[s]
        if kept[p] >= top_k:
            continue
        th, ph = thetas[s, m], phis[s, m]
        same = False
        for q in range(out):
            if (
                out_pair[q] == p
                and abs(np.sin(0.5 * (th - out_t[q, 1]))) < 1e-3
                and abs(np.sin(0.5 * (ph - out_R[q, 1, 0]))) < 1e-3
            ):
                same = True
                break
        if same:
            continue
        # (θ, φ) are parked in unused entries until the matrices are written below.
        out_t[out, 1] = th
        out_R[out, 1, 0] = ph
        out_pair[out] = p
        kept[p] += 1
        out += 1
    for q in range(out):
        planar_pose_into(out_t[q, 1], out_R[q, 1, 0], out_R[q], out_t[q])
    return out


@njit(cache=True, error_model="numpy")
def _majority_in_front(
    rho: float,
    lo: np.ndarray,
    hi: np.ndarray,
    row: np.ndarray,
    row_pair: np.ndarray,
    Rkq: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    xq: np.ndarray,
    xr: np.ndarray,
) -> bool:
    """Pdcheck of a consensus scale: at least half of the matches voting for ``rho`` (their
    interval contains it) triangulate in front of the query and their reference
    (``k_from_query = (Rkq[k], ρ a[k] + b[k])``)."""
    votes = 0
    front = 0
    tk = np.empty(3)
    for q in range(row.shape[0]):
        if not (lo[q] < rho < hi[q]):
            continue
        k = row_pair[q]
        for d in range(3):
            tk[d] = rho * a[k, d] + b[k, d]
        votes += 1
        if _positive_depths(Rkq[k], tk, xq[row[q]], xr[row[q]]):
            front += 1
    return 2 * front >= votes


@njit(cache=True, error_model="numpy")
def hypotheses_2p1p_consensus(
    Rrel: np.ndarray,
    trel: np.ndarray,
    prel: np.ndarray,
    xq: np.ndarray,
    xr: np.ndarray,
    offsets: np.ndarray,
    f_query: np.ndarray,
    f_ref: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    threshold_sq: float,
    peaks: int,
    max_votes: int,
    out_R: np.ndarray,
    out_t: np.ndarray,
    counters: np.ndarray,
) -> int:
    """Stage 2 of the consensus 2p1p: the scale of each relative pose from all other matches.

    Given ``j_from_query = (R, ρ t̃)``, a match of another pair ``k`` has (paper eq. 16-18) the
    epipolar residual ``x_kᵀ [ρ a + b]x y = α + β ρ`` with ``a = R_kj t̃``, ``b = t_kj``,
    ``y = R_kj R x_q``, and a Sampson denominator quadratic in ``ρ``. Its Sampson error is
    below τ exactly on the interval(s) of ``ρ`` where ``(α + βρ)² − τ² den(ρ) < 0`` — a
    quadratic inequality solved in closed form. Instead of drawing one third match at random
    (eq. 18 for one match), the ρ covered by the most intervals (the largest 1D consensus,
    found by sweeping the sorted interval ends) is taken: every match of the other pairs votes.
    Matches of pair ``j`` do not depend on ρ. Up to ``peaks`` separated maxima are returned.

    Args:
        Rrel, trel, prel: (C, 3, 3), (C, 3), (C,) relative poses ``ref_from_query`` of pair prel
            (unit translation), e.g. from :func:`planar_relative_candidates`.
        threshold_sq: τ² in pixels².
        max_votes: with more matches in the other pairs than this, every s-th match of each
            pair votes (s = ⌈others / max_votes⌉): a hundred votes find the peak as well as
            a thousand, and the cost is linear in the votes.
        out_R, out_t: (C * peaks, ...) ``query_from_world`` outputs.

    Returns:
        number of hypotheses written. A relative pose without any interval (all other
        matches insensitive to ρ: query collinear with the reference centres) counts as
        degenerate; a maximum at ρ ≤ 0, or one where most of its voters triangulate behind a
        camera, is rejected by Pdcheck.
    """
    N = xq.shape[0]
    used_lo = np.empty(peaks)
    used_hi = np.empty(peaks)
    lo = np.empty(N)
    hi = np.empty(N)
    row = np.empty(N, dtype=np.int64)
    row_pair = np.empty(N, dtype=np.int64)
    P = offsets.shape[0] - 1
    Rkq_all = np.empty((P, 3, 3))
    a_all = np.empty((P, 3))
    b_all = np.empty((P, 3))
    # k_from_j of every two references (R_kj, t_kj): shared by all relative poses of pair j.
    R_kj = np.empty((P, P, 3, 3))
    t_kj = np.empty((P, P, 3))
    for j in range(P):
        for k in range(P):
            R_kj[j, k] = m3.mul_t(ref_R[k], ref_R[j])
            t_kj[j, k] = ref_t[k] - m3.vec(R_kj[j, k], ref_t[j])
    fq0, fq1 = f_query[0], f_query[1]
    tau2 = threshold_sq
    out = 0
    for c in range(Rrel.shape[0]):
        j = prel[c]
        R = Rrel[c]
        tt = trel[c]
        Rj, tj = ref_R[j], ref_t[j]
        others = N - (offsets[j + 1] - offsets[j])
        stride = max(1, (others + max_votes - 1) // max_votes)
        m = 0
        for k in range(P):
            if k == j:
                continue
            R21 = R_kj[j, k]
            Rkq = Rkq_all[k]
            for r in range(3):  # Rkq = R21 R, a = R21 t̃ (in place: no allocation per pair)
                a_all[k, r] = R21[r, 0] * tt[0] + R21[r, 1] * tt[1] + R21[r, 2] * tt[2]
                for q in range(3):
                    Rkq[r, q] = R21[r, 0] * R[0, q] + R21[r, 1] * R[1, q] + R21[r, 2] * R[2, q]
            b_all[k] = t_kj[j, k]
            a, b = a_all[k], b_all[k]
            a0, a1, a2 = a[0], a[1], a[2]
            b0, b1, b2 = b[0], b[1], b[2]
            ifr0, ifr1 = 1.0 / f_ref[k, 0], 1.0 / f_ref[k, 1]
            # Eᵀ x_k = Rkqᵀ (x_k × t), t = ρ a + b: only its first two entries enter den, and
            # column c of Rkq dotted with x × a is x · (a × Rkq[:, c]): per pair, 4 vectors.
            ifq0, ifq1 = 1.0 / fq0, 1.0 / fq1
            c00, c10, c20 = Rkq[0, 0] * ifq0, Rkq[1, 0] * ifq0, Rkq[2, 0] * ifq0
            c01, c11, c21 = Rkq[0, 1] * ifq1, Rkq[1, 1] * ifq1, Rkq[2, 1] * ifq1
            ga0, ga1, ga2 = a1 * c20 - a2 * c10, a2 * c00 - a0 * c20, a0 * c10 - a1 * c00
            gb0, gb1, gb2 = a1 * c21 - a2 * c11, a2 * c01 - a0 * c21, a0 * c11 - a1 * c01
            ha0, ha1, ha2 = b1 * c20 - b2 * c10, b2 * c00 - b0 * c20, b0 * c10 - b1 * c00
            hb0, hb1, hb2 = b1 * c21 - b2 * c11, b2 * c01 - b0 * c21, b0 * c11 - b1 * c01
            for i in range(offsets[k], offsets[k + 1], stride):
                q0, q1, q2 = xq[i, 0], xq[i, 1], xq[i, 2]
                y0 = Rkq[0, 0] * q0 + Rkq[0, 1] * q1 + Rkq[0, 2] * q2
                y1 = Rkq[1, 0] * q0 + Rkq[1, 1] * q1 + Rkq[1, 2] * q2
                y2 = Rkq[2, 0] * q0 + Rkq[2, 1] * q1 + Rkq[2, 2] * q2
                x0, x1, x2 = xr[i, 0], xr[i, 1], xr[i, 2]
                ay0, ay1, ay2 = a1 * y2 - a2 * y1, a2 * y0 - a0 * y2, a0 * y1 - a1 * y0
                by0, by1, by2 = b1 * y2 - b2 * y1, b2 * y0 - b0 * y2, b0 * y1 - b1 * y0
                beta = x0 * ay0 + x1 * ay1 + x2 * ay2
                alpha = x0 * by0 + x1 * by1 + x2 * by2
                g0 = x0 * ga0 + x1 * ga1 + x2 * ga2
                g1 = x0 * gb0 + x1 * gb1 + x2 * gb2
                h0 = x0 * ha0 + x1 * ha1 + x2 * ha2
                h1 = x0 * hb0 + x1 * hb1 + x2 * hb2
                v0, v1 = ay0 * ifr0, ay1 * ifr1
                u0, u1 = by0 * ifr0, by1 * ifr1
                vv = v0 * v0 + v1 * v1 + g0 * g0 + g1 * g1
                uv = u0 * v0 + u1 * v1 + h0 * g0 + h1 * g1
                uu = u0 * u0 + u1 * u1 + h0 * h0 + h1 * h1
                A = beta * beta - tau2 * vv
                B = 2.0 * (alpha * beta - tau2 * uv)
                C = alpha * alpha - tau2 * uu
                if not A > 1e-12 * beta * beta:
                    continue  # inlier for every large ρ: no information on the scale
                disc = B * B - 4.0 * A * C
                if disc <= 0.0:
                    continue
                sd = np.sqrt(disc)
                r2 = (-B + sd) / (2.0 * A)
                if r2 <= 0.0:
                    continue
                lo[m] = max((-B - sd) / (2.0 * A), 0.0)
                hi[m] = r2
                row[m] = i
                row_pair[m] = k
                m += 1
        if m == 0:
            counters[HYPOTHESES] += 1
            counters[DEGENERATE] += 1
            continue
        # Sweep the sorted starts and ends (two sorts of m values: cheaper than sorting 2m
        # events); the depth after a start is the number of intervals covering the segment
        # up to the next event. Ties: an end before a start at the same ρ.
        slo = np.sort(lo[:m])
        shi = np.sort(hi[:m])
        best_found = 0
        for _peak in range(peaks):
            depth = 0
            best = 0
            best_lo = 0.0
            best_hi = 0.0
            i = 0
            e = 0
            while i < m:
                if not slo[i] < shi[e]:
                    depth -= 1
                    e += 1
                    continue
                depth += 1
                a_lo = slo[i]
                i += 1
                if depth > best:
                    a_hi = shi[e] if i == m else min(slo[i], shi[e])
                    mid = 0.5 * (a_lo + a_hi)
                    clash = False
                    for u in range(best_found):
                        if used_lo[u] <= mid <= used_hi[u]:
                            clash = True
                            break
                    if clash:
                        continue
                    best = depth
                    best_lo, best_hi = a_lo, a_hi
            if best == 0:
                break
            rho = 0.5 * (best_lo + best_hi)
            # Suppress the neighbourhood of this maximum (±10 % of ρ) for the next peak.
            used_lo[best_found] = rho * 0.9
            used_hi[best_found] = rho * 1.1
            best_found += 1
            counters[HYPOTHESES] += 1
            in_front = rho > 0.0 and _majority_in_front(
                rho, lo[:m], hi[:m], row[:m], row_pair[:m], Rkq_all, a_all, b_all, xq, xr
            )
            out = _emit_planar(rho, in_front, R, tt, Rj, tj, out_R, out_t, out, counters)
    return out
