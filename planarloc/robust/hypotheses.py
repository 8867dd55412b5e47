"""Absolute-pose hypotheses from minimal samples, with the paper's multiple checking (numba).

Counters (indices into the ``counters`` array): 0 hypotheses, 1 rejected by Rcheck (eq. 12),
2 rejected by Pdcheck (ρ ≤ 0 or a negative depth), 3 rejected by the consistency check,
4 degenerate (no finite solution). The 2p1p hypotheses whose scale all other matches vote on are
in :mod:`planarloc.robust.consensus_scale`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.robust.problem import ProblemArrays
from planarloc.solvers.abspose_2p1p import scale_2p1p, scale_from_point3d
from planarloc.solvers.abspose_2p2p import triangulate_scales
from planarloc.solvers.abspose_p3p import MAX_SOLUTIONS as P3P_MAX_SOLUTIONS
from planarloc.solvers.abspose_p3p import solve_p3p
from planarloc.solvers.abspose_up2p import solve_up2p
from planarloc.solvers.relpose_planar_2p import solve_planar_2p

HYPOTHESES, RCHECK, PDCHECK, CONSISTENCY, DEGENERATE = range(5)


class RelativePoses(NamedTuple):
    """Candidate relative poses ``ref_from_query`` of S samples, A per sample, as one record for
    the kernels: R (S, A, 3, 3), t (S, A, 3) unit translations, valid (S, A) bool."""

    R: np.ndarray
    t: np.ndarray
    valid: np.ndarray


class Hypotheses(NamedTuple):
    """The output of the hypothesis kernels as one record: R (H, 3, 3), t (H, 3) rows for
    ``query_from_world`` hypotheses, and the (5,) int64 counters (indices above), incremented."""

    R: np.ndarray
    t: np.ndarray
    counters: np.ndarray

    @classmethod
    def empty(cls, rows: int, counters: np.ndarray) -> Hypotheses:
        """Room for ``rows`` hypotheses, counting into ``counters``."""
        return cls(np.empty((rows, 3, 3)), np.empty((rows, 3)), counters)

    def first(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``m`` hypotheses a kernel wrote: R (m, 3, 3), t (m, 3)."""
        return self.R[:m], self.t[:m]


@njit(cache=True, error_model="numpy", inline="always")
def positive_depths(R: np.ndarray, t: np.ndarray, xq: np.ndarray, xr: np.ndarray) -> bool:
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
def emit_planar(
    rho: float,
    in_front: bool,
    R: np.ndarray,
    tt: np.ndarray,
    Rj: np.ndarray,
    tj: np.ndarray,
    dest: Hypotheses,
    out: int,
) -> int:
    """Pdcheck of a scaled planar relative pose, then its ``query_from_world`` at ``out``.

    ``j_from_query = (R, ρ t̃)`` with reference ``j_from_world = (Rj, tj)`` gives
    ``query_from_world = (Rᵀ Rj, Rᵀ (tj − ρ t̃))``. Rejected (counted as Pdcheck) unless ρ > 0
    and ``in_front`` (the caller's cheirality test).

    Returns:
        the next free output row.
    """
    if not (rho > 0.0 and in_front):
        dest.counters[PDCHECK] += 1
        return out
    m3.store_pose(dest.R, dest.t, out, m3.t_mul(R, Rj), m3.t_vec(R, tj - rho * tt))
    return out + 1


@njit(cache=True, error_model="numpy")
def hypotheses_2p1p(
    samples: np.ndarray,
    third_is_3d: np.ndarray,
    pj: np.ndarray,
    pk: np.ndarray,
    prob: ProblemArrays,
    dest: Hypotheses,
) -> int:
    """2p1p hypotheses (paper Sec. IV-C) with Pdcheck.

    Args:
        samples: (S, 3) rows ``(i1, i2, i3)``: two matches of pair ``pj`` and the third, a
            match row of pair ``pk`` or, where ``third_is_3d``, a row of ``xq3d``/``X3d``
            (structure mode: scale from a 2D-3D constraint, same unknown ρ).
        pj, pk: (S,) the pairs of the two matches and of the third (unused where ``third_is_3d``).
        prob: the problem's arrays (matches, reference poses, 2D-3D constraints).
        dest: room for 2S hypotheses (:class:`Hypotheses`).

    Returns:
        number of hypotheses written.
    """
    xq, xr, ref_R, ref_t, xq3d, X3d = prob.xq, prob.xr, prob.ref_R, prob.ref_t, prob.xq3d, prob.X3d
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
        for d in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            sq[0, d], sq[1, d] = xq[i1, d], xq[i2, d]
            sr[0, d], sr[1, d] = xr[i1, d], xr[i2, d]
        n = solve_planar_2p(sq, sr, thetas, phis)
        if n == 0:
            dest.counters[DEGENERATE] += 1
            continue
        j = pj[s]
        Rj, tj = ref_R[j], ref_t[j]
        for m in range(n):
            dest.counters[HYPOTHESES] += 1
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
                in_front = rho > 0 and positive_depths(m3.mul(R21, R), rho * a + t21, xq[i3], xr[i3])
            if rho != rho:
                dest.counters[DEGENERATE] += 1
                continue
            out = emit_planar(rho, in_front, R, tt, Rj, tj, dest, out)
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_from_relative_poses(
    rel_j: RelativePoses,
    rel_k: RelativePoses,
    pj: np.ndarray,
    pk: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    cos_rcheck: float,
    cos_consistency: float,
    dest: Hypotheses,
) -> int:
    """Absolute hypotheses from relative poses to two references (2p2p and the baselines).

    Paper Sec. IV-B: Rcheck (eq. 12), triangulation (eq. 13-15) and Pdcheck, consistency.

    Args:
        rel_j: (S, A) candidate ``j_from_query`` per sample (unit ``t``), with valid flags;
            rel_k likewise for ``k_from_query``.
        pj, pk: (S,) the two pairs of each sample.
        ref_R, ref_t: (P, 3, 3), (P, 3) reference ``cam_from_world``.
        cos_rcheck, cos_consistency: cosines of ``e_th`` and ``α_th``.

    Returns:
        number of ``query_from_world`` hypotheses written to ``dest``.
    """
    Ra, ta, va = rel_j
    Rb, tb, vb = rel_k
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
                dest.counters[HYPOTHESES] += 1
                Rab = m3.mul_t(Ra[s, a], Rb[s, b])
                cos_e = 0.5 * (np.sum(R12 * Rab) - 1.0)  # tr(R12 Rabᵀ) = Σ R12 ∘ Rab
                if cos_e < cos_rcheck:
                    dest.counters[RCHECK] += 1
                    continue
                t2_in_1 = m3.vec(Rab, tb[s, b])
                rho, rho2, reg = triangulate_scales(ta[s, a], t2_in_1, t12)
                if reg:
                    dest.counters[DEGENERATE] += 1
                    continue
                if rho <= 0 or rho2 <= 0:
                    dest.counters[PDCHECK] += 1
                    continue
                Rq = m3.t_mul(Ra[s, a], Rj)
                tq = m3.t_vec(Ra[s, a], tj - rho * ta[s, a])
                cq = -m3.t_vec(Rq, tq)
                that = m3.vec(Rk, cq) + tk  # query centre seen from k; must point along t̃₂
                nt = np.sqrt(np.sum(that * that))
                if nt < 1e-12 or np.sum(that * tb[s, b]) / nt < cos_consistency:
                    dest.counters[CONSISTENCY] += 1
                    continue
                m3.store_pose(dest.R, dest.t, out, Rq, tq)
                out += 1
        if not any_valid:
            dest.counters[DEGENERATE] += 1
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_up2p(samples: np.ndarray, pj: np.ndarray, prob: ProblemArrays, dest: Hypotheses) -> int:
    """Upright P2P hypotheses (structure mode): two 2D-3D constraints, yaw relative to pair ``pj``.

    Args:
        samples: (S, 2) rows of ``prob.xq3d`` / ``prob.X3d``.
        pj: (S,) the reference whose frame is upright relative to the query (local planar motion).
        prob: the problem's arrays (reference poses, 2D-3D constraints).
        dest: room for 2S hypotheses (:class:`Hypotheses`).
    """
    ref_R, ref_t, xq3d, X3d = prob.ref_R, prob.ref_t, prob.xq3d, prob.X3d
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
            Xk = m3.vec(Rj, X3d[samples[s, k]])
            for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
                x[k, a] = xq3d[samples[s, k], a]
                X[k, a] = Xk[a] + tj[a]
        n = solve_up2p(x, X, th, ts)
        if n == 0:
            dest.counters[DEGENERATE] += 1
            continue
        for m in range(n):
            dest.counters[HYPOTHESES] += 1
            c, sn = np.cos(th[m]), np.sin(th[m])
            R[0, 0], R[0, 2], R[2, 0], R[2, 2] = c, -sn, sn, c
            m3.store_pose(dest.R, dest.t, out, m3.mul(R, Rj), m3.vec(R, tj) + ts[m])
            out += 1
    return out


@njit(cache=True, error_model="numpy")
def hypotheses_p3p(samples: np.ndarray, prob: ProblemArrays, dest: Hypotheses) -> int:
    """6DoF P3P hypotheses from three 2D-3D constraints (:mod:`planarloc.solvers.abspose_p3p`).

    Args:
        samples: (S, 3) rows of ``prob.xq3d`` / ``prob.X3d``.
        prob: the problem's arrays (2D-3D constraints).
        dest: room for 4S hypotheses (:class:`Hypotheses`).

    Returns:
        number of hypotheses written.
    """
    Rs = np.empty((P3P_MAX_SOLUTIONS, 3, 3))
    ts = np.empty((P3P_MAX_SOLUTIONS, 3))
    out = 0
    for s in range(samples.shape[0]):
        n = solve_p3p(prob.xq3d[samples[s]], prob.X3d[samples[s]], Rs, ts)
        if n == 0:
            dest.counters[DEGENERATE] += 1
            continue
        dest.counters[HYPOTHESES] += n
        for k in range(n):  # element loops: a 3-D slice assignment compiles numba's shape-error formatting
            for a in range(3):
                dest.t[out + k, a] = ts[k, a]
                for b in range(3):
                    dest.R[out + k, a, b] = Rs[k, a, b]
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
            m3.store_pose(out_R[pair], out_t[pair], k, R[s_, a_], t[s_, a_])
            k += 1
        out_count[pair] = k
