"""2p1p hypotheses with the scale chosen by consensus instead of one random third match (numba).

Stage 1 (:func:`planar_relative_candidates`): per pair, the best distinct planar relative poses
of two-match samples. Stage 2 (:func:`hypotheses_2p1p_consensus`): the scale of each from every
match of the other pairs at once (paper eq. 16-18 for each of them), the scale most of them agree
on is the hypothesis. The counters are those of :mod:`planarloc.robust.hypotheses`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.epipolar_kernels import sampson_sq
from planarloc.robust.hypotheses import DEGENERATE, HYPOTHESES, Hypotheses, emit_planar, positive_depths
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.sampling import draw_pair_samples
from planarloc.solvers.relpose_planar_2p import planar_pose_into, solve_planar_2p


class ConsensusSettings(NamedTuple):
    """The settings of both stages, as one record.

    Attributes:
        threshold_sq: MSAC threshold τ² (pixels²).
        top_k: relative poses kept per pair (stage 1).
        max_scored: stage 1 scores a pair with more matches on every s-th (s = ⌈n / max_scored⌉);
            ranking relative poses needs no more.
        peaks: separated scale maxima returned per relative pose (stage 2).
        max_votes: with more matches in the other pairs than this, every s-th match of each
            pair votes (s = ⌈others / max_votes⌉; stage 2): a hundred votes find the peak as well
            as a thousand, and the cost is linear in the votes.
    """

    threshold_sq: float
    top_k: int
    max_scored: int
    peaks: int
    max_votes: int


class RelativeCandidates(NamedTuple):
    """Stage 1's output and stage 2's input as one record: R (C, 3, 3) rotations and t (C, 3) unit
    translations of relative poses ``ref_from_query`` of pair ``pair`` (C,), and the (5,) int64
    counters of :mod:`planarloc.robust.hypotheses` that stage 1 increments."""

    R: np.ndarray
    t: np.ndarray
    pair: np.ndarray
    counters: np.ndarray

    @classmethod
    def empty(cls, rows: int, counters: np.ndarray) -> RelativeCandidates:
        """Room for ``rows`` relative poses, counting into ``counters``."""
        return cls(np.empty((rows, 3, 3)), np.empty((rows, 3)), np.empty(rows, dtype=np.int64), counters)

    def first(self, m: int) -> RelativeCandidates:
        """The ``m`` relative poses stage 1 wrote."""
        return RelativeCandidates(self.R[:m], self.t[:m], self.pair[:m], self.counters)


class PairMotions(NamedTuple):
    """Every pair's motion under one unit relative pose of pair j and the unknown scale ρ:
    ``k_from_query = (R[k], ρ a[k] + b[k])`` (paper eq. 16-18: ``a = R_kj t̃``, ``b = t_kj``).

    Attributes:
        R: (P, 3, 3) ``R_kj R``; a, b: (P, 3) (rows of pair j unused).
    """

    R: np.ndarray
    a: np.ndarray
    b: np.ndarray


class ScaleVotes(NamedTuple):
    """The votes of the matches for the scale: match ``m`` is an inlier for ρ in
    ``(lo[m], hi[m])``; ``row[m]`` is its match row and ``pair[m]`` its pair. (N,) each."""

    lo: np.ndarray
    hi: np.ndarray
    row: np.ndarray
    pair: np.ndarray


@njit(cache=True, error_model="numpy", inline="always")
def _planar_essential_into(theta: float, phi: float, E: np.ndarray) -> None:
    """``E = [t]x R`` of the paper's (θ, φ) (eq. 1-2, ρ = 1) into E (3, 3)."""
    c, sn = np.cos(theta), np.sin(theta)
    sp, cp = np.sin(phi), np.cos(phi)
    t0 = -(c * sp - sn * cp)
    t2 = -(sn * sp + c * cp)
    # E = [t]x R with R = [[c, 0, -s], [0, 1, 0], [s, 0, c]], t = (t0, 0, t2)
    E[0, 0], E[0, 1], E[0, 2] = 0.0, -t2, 0.0
    E[1, 0], E[1, 1], E[1, 2] = t2 * c - t0 * sn, 0.0, -t2 * sn - t0 * c
    E[2, 0], E[2, 1], E[2, 2] = 0.0, t0, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _insert_sorted(smallest: np.ndarray, value: float) -> None:
    """Insert ``value`` into the ascending ``smallest`` (K,), dropping its last entry."""
    q = smallest.shape[0] - 1
    while q > 0 and smallest[q - 1] > value:
        smallest[q] = smallest[q - 1]
        q -= 1
    smallest[q] = value


@njit(cache=True, error_model="numpy", inline="always")
def _score_planar_samples(
    samples: np.ndarray,
    prob: ProblemArrays,
    settings: ConsensusSettings,
    thetas: np.ndarray,
    phis: np.ndarray,
    cost: np.ndarray,
    counters: np.ndarray,
) -> None:
    """Solve every sample (``thetas``, ``phis`` (S, 2)) and score its solutions by MSAC on (every
    s-th match of, see :func:`planar_relative_candidates`) its own pair (``cost`` (2S,), left inf
    for a solution that cannot be among its pair's ``top_k``)."""
    threshold_sq, top_k, max_scored = settings.threshold_sq, settings.top_k, settings.max_scored
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    P = offsets.shape[0] - 1
    # Per pair, the top_k smallest costs so far (ascending): a candidate whose partial cost
    # exceeds the last cannot be kept, so its scoring stops early (most samples hold an outlier).
    bound = np.full((P, top_k), np.inf)
    sq = np.empty((2, 3))
    sr = np.empty((2, 3))
    E = np.empty((3, 3))
    for s in range(samples.shape[0]):
        sq[0], sq[1] = xq[samples[s, 0]], xq[samples[s, 1]]
        sr[0], sr[1] = xr[samples[s, 0]], xr[samples[s, 1]]
        n = solve_planar_2p(sq, sr, thetas[s], phis[s])
        if n == 0:
            counters[DEGENERATE] += 1
        p = prob.pair[samples[s, 0]]
        for m in range(n):  # relative poses are not counted as hypotheses; stage 2 counts those
            _planar_essential_into(thetas[s, m], phis[s, m], E)
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
            _insert_sorted(bound[p], acc)


@njit(cache=True, error_model="numpy", inline="always")
def _keep_distinct(
    cost: np.ndarray,
    thetas: np.ndarray,
    phis: np.ndarray,
    samples: np.ndarray,
    prob: ProblemArrays,
    top_k: int,
    out: RelativeCandidates,
) -> int:
    """Per pair, the ``top_k`` cheapest solutions that differ from each other; their (θ, φ) are
    parked in ``out.t[q, 1]``, ``out.R[q, 1, 0]`` (entries the pose matrices overwrite later)."""
    out_R, out_t, out_pair = out.R, out.t, out.pair
    order = np.argsort(cost)
    found = 0
    kept = np.zeros(prob.offsets.shape[0] - 1, dtype=np.int64)
    for o in order:
        if not cost[o] < np.inf:
            break
        s, m = o // 2, o % 2
        p = prob.pair[samples[s, 0]]
        if kept[p] >= top_k:
            continue
        th, ph = thetas[s, m], phis[s, m]
        same = False
        for q in range(found):
            if (
                out_pair[q] == p
                and abs(np.sin(0.5 * (th - out_t[q, 1]))) < 1e-3
                and abs(np.sin(0.5 * (ph - out_R[q, 1, 0]))) < 1e-3
            ):
                same = True
                break
        if same:
            continue
        out_t[found, 1] = th
        out_R[found, 1, 0] = ph
        out_pair[found] = p
        kept[p] += 1
        found += 1
    return found


@njit(cache=True, error_model="numpy")
def planar_relative_candidates(
    samples: np.ndarray, prob: ProblemArrays, settings: ConsensusSettings, out: RelativeCandidates
) -> int:
    """Stage 1 of the consensus 2p1p: per pair, the ``top_k`` best distinct planar relative poses.

    Every sample's planar 2p solutions (paper Sec. IV-A) are scored by MSAC over the matches of
    their own pair; per pair the ``top_k`` cheapest that differ from each other (in rotation
    or translation direction) are kept.

    Args:
        samples: (S, 2) match rows, both of one pair.
        prob: the problem's arrays (matches, pairs, offsets, focal lengths).
        settings: ``threshold_sq``, ``top_k`` and ``max_scored`` (:class:`ConsensusSettings`).
        out: room for P * top_k relative poses (:class:`RelativeCandidates`).

    Returns:
        number of relative poses written.
    """
    S = samples.shape[0]
    thetas = np.empty((S, 2))
    phis = np.empty((S, 2))
    cost = np.full(2 * S, np.inf)
    _score_planar_samples(samples, prob, settings, thetas, phis, cost, out.counters)
    found = _keep_distinct(cost, thetas, phis, samples, prob, settings.top_k, out)
    for q in range(found):
        planar_pose_into(out.t[q, 1], out.R[q, 1, 0], out.R[q], out.t[q])
    return found


@njit(cache=True, error_model="numpy", inline="always")
def _majority_in_front(
    rho: float, votes: ScaleVotes, m: int, motions: PairMotions, xq: np.ndarray, xr: np.ndarray
) -> bool:
    """Pdcheck of a consensus scale: at least half of the first ``m`` votes for ``rho`` (their
    interval contains it) triangulate in front of the query and their reference."""
    n_votes = 0
    front = 0
    tk = np.empty(3)
    for q in range(m):
        if not (votes.lo[q] < rho < votes.hi[q]):
            continue
        k = votes.pair[q]
        for d in range(3):
            tk[d] = rho * motions.a[k, d] + motions.b[k, d]
        n_votes += 1
        if positive_depths(motions.R[k], tk, xq[votes.row[q]], xr[votes.row[q]]):
            front += 1
    return 2 * front >= n_votes


@njit(cache=True, error_model="numpy", inline="always")
def _reference_motions(ref_R: np.ndarray, ref_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``k_from_j = (R_kj[j, k], t_kj[j, k])`` of every two references: (P, P, 3, 3), (P, P, 3)."""
    P = ref_R.shape[0]
    R_kj = np.empty((P, P, 3, 3))
    t_kj = np.empty((P, P, 3))
    for j in range(P):
        for k in range(P):
            Rkj = m3.mul_t(ref_R[k], ref_R[j])
            m3.store_pose(R_kj[j], t_kj[j], k, Rkj, ref_t[k] - m3.vec(Rkj, ref_t[j]))
    return R_kj, t_kj


@njit(cache=True, error_model="numpy", inline="always")
def _scale_votes(
    j: int,
    R: np.ndarray,
    tt: np.ndarray,
    R_kj: np.ndarray,
    t_kj: np.ndarray,
    prob: ProblemArrays,
    stride: int,
    tau2: float,
    motions: PairMotions,
    votes: ScaleVotes,
) -> int:
    """The votes for the scale of ``j_from_query = (R, ρ tt)``: every other pair's motion into
    ``motions`` and the scale intervals of every ``stride``-th of its matches into ``votes`` (see
    :func:`hypotheses_2p1p_consensus`); returns the number of votes."""
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    lo, hi, row, row_pair = votes.lo, votes.hi, votes.row, votes.pair
    Rkq_all, a_all, b_all = motions.R, motions.a, motions.b
    m = 0
    for k in range(offsets.shape[0] - 1):
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
        ifq0, ifq1 = 1.0 / f_query[0], 1.0 / f_query[1]
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
    return m


@njit(cache=True, error_model="numpy", inline="always")
def _densest_segment(
    slo: np.ndarray, shi: np.ndarray, used_lo: np.ndarray, used_hi: np.ndarray, num_used: int
) -> tuple[int, float, float]:
    """The segment of ρ covered by the most intervals (sorted starts ``slo``, sorted ends
    ``shi``) whose middle is outside the first ``num_used`` suppressed ranges: (its depth, 0
    if none; its ends).

    Sweeps the sorted starts and ends (two sorts of m values: cheaper than sorting 2m events);
    the depth after a start is the number of intervals covering the segment up to the next
    event. Ties: an end before a start at the same ρ."""
    m = slo.shape[0]
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
            for u in range(num_used):
                if used_lo[u] <= mid <= used_hi[u]:
                    clash = True
                    break
            if clash:
                continue
            best = depth
            best_lo, best_hi = a_lo, a_hi
    return best, best_lo, best_hi


@njit(cache=True, error_model="numpy")
def hypotheses_2p1p_consensus(
    rel: RelativeCandidates, prob: ProblemArrays, settings: ConsensusSettings, dest: Hypotheses
) -> int:
    """Stage 2 of the consensus 2p1p: the scale of each relative pose from all other matches.

    Given ``j_from_query = (R, ρ t̃)``, a match of another pair ``k`` has (paper eq. 16-18) the
    epipolar residual ``x_kᵀ [ρ a + b]x y = α + β ρ`` with ``a = R_kj t̃``, ``b = t_kj``,
    ``y = R_kj R x_q``, and a Sampson denominator quadratic in ``ρ``. Its Sampson error is
    below τ exactly on the interval(s) of ``ρ`` where ``(α + βρ)² − τ² den(ρ) < 0`` — a
    quadratic inequality solved in closed form. Instead of drawing one third match at random
    (eq. 18 for one match), the ρ covered by the most intervals (the largest 1D consensus,
    found by sweeping the sorted interval ends) is taken: every match of the other pairs votes.
    Matches of pair ``j`` do not depend on ρ. Up to ``settings.peaks`` separated maxima are
    returned.

    Args:
        rel: C relative poses ``ref_from_query`` (unit translation), e.g. from
            :func:`planar_relative_candidates`.
        prob: the problem's arrays (matches, offsets, focal lengths, reference poses).
        settings: ``threshold_sq`` (τ², pixels²), ``peaks`` and ``max_votes``
            (:class:`ConsensusSettings`).
        dest: room for C * peaks hypotheses (:class:`~planarloc.robust.hypotheses.Hypotheses`).

    Returns:
        number of hypotheses written. A relative pose without any interval (all other
        matches insensitive to ρ: query collinear with the reference centres) counts as
        degenerate; a maximum at ρ ≤ 0, or one where most of its voters triangulate behind a
        camera, is rejected by Pdcheck.
    """
    Rrel, trel, prel = rel.R, rel.t, rel.pair
    threshold_sq, peaks, max_votes = settings.threshold_sq, settings.peaks, settings.max_votes
    offsets = prob.offsets
    N = prob.xq.shape[0]
    P = offsets.shape[0] - 1
    used_lo = np.empty(peaks)
    used_hi = np.empty(peaks)
    votes = ScaleVotes(np.empty(N), np.empty(N), np.empty(N, dtype=np.int64), np.empty(N, dtype=np.int64))
    motions = PairMotions(np.empty((P, 3, 3)), np.empty((P, 3)), np.empty((P, 3)))
    # k_from_j of every two references (R_kj, t_kj): shared by all relative poses of pair j.
    R_kj, t_kj = _reference_motions(prob.ref_R, prob.ref_t)
    out = 0
    for c in range(Rrel.shape[0]):
        j = prel[c]
        R = Rrel[c]
        tt = trel[c]
        others = N - (offsets[j + 1] - offsets[j])
        stride = max(1, (others + max_votes - 1) // max_votes)
        m = _scale_votes(j, R, tt, R_kj, t_kj, prob, stride, threshold_sq, motions, votes)
        if m == 0:
            dest.counters[HYPOTHESES] += 1
            dest.counters[DEGENERATE] += 1
            continue
        slo = np.sort(votes.lo[:m])
        shi = np.sort(votes.hi[:m])
        for found in range(peaks):
            best, best_lo, best_hi = _densest_segment(slo, shi, used_lo, used_hi, found)
            if best == 0:
                break
            rho = 0.5 * (best_lo + best_hi)
            # Suppress the neighbourhood of this maximum (±10 % of ρ) for the next peak.
            used_lo[found] = rho * 0.9
            used_hi[found] = rho * 1.1
            dest.counters[HYPOTHESES] += 1
            in_front = rho > 0.0 and _majority_in_front(rho, votes, m, motions, prob.xq, prob.xr)
            out = emit_planar(rho, in_front, R, tt, prob.ref_R[j], prob.ref_t[j], dest, out)
    return out


@njit(cache=True, error_model="numpy")
def consensus_2p1p(
    u: np.ndarray, prob: ProblemArrays, settings: ConsensusSettings, counters: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Both stages in one call: ``len(u)`` samples of two matches of one pair each (the pair drawn
    in proportion to its matches, :func:`~planarloc.robust.sampling.draw_pair_samples`), then
    :func:`planar_relative_candidates` and :func:`hypotheses_2p1p_consensus` on them. The same
    kernels the estimator called one by one from Python (the same hypotheses to the bit) without
    the numpy calls between them (~30 µs of a hard-protocol query, benchmarks/estimator_profile.py).

    Args:
        u: (S, 4) uniform variates.
        counters: (5,) the hypothesis counters, incremented.

    Returns:
        ``query_from_world`` hypotheses R (H, 3, 3), t (H, 3).
    """
    n = u.shape[0]
    samples = np.empty((n, 2), dtype=np.int64)
    sample_pair = np.empty(n, dtype=np.int64)
    draw_pair_samples(u, prob.offsets, 2, 0, samples, sample_pair, np.empty(n, dtype=np.int64))
    rows = settings.top_k * (prob.offsets.shape[0] - 1)
    candidates = RelativeCandidates(
        np.empty((rows, 3, 3)), np.empty((rows, 3)), np.empty(rows, dtype=np.int64), counters
    )
    c = planar_relative_candidates(samples, prob, settings, candidates)
    found = Hypotheses(np.empty((c * settings.peaks, 3, 3)), np.empty((c * settings.peaks, 3)), counters)
    kept = RelativeCandidates(candidates.R[:c], candidates.t[:c], candidates.pair[:c], counters)
    m = hypotheses_2p1p_consensus(kept, prob, settings, found)
    return found.R[:m], found.t[:m]
