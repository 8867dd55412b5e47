"""Refinement with the map's pose uncertainty: the reference poses as nuisance parameters.

A map pose error is systematic: every match of that reference sees it. When the query is nearly
collinear with the reference centres (roads, corridors), a 0.1° rotation error of one reference
moves the 2D-2D optimum by metres along the line, so thousands of 2D-2D matches must not
outvote a few hundred 2D-3D constraints that pin the position. Generalised least squares does
exactly that: each reference ``p`` gets a correction ``δ_p = (ω_p, d_p)`` (rotation increment
``R_p' = Exp(ω_p) R_p`` and centre shift ``d_p``) with the prior ``δ_p ~ N(0, diag(σ_rot², σ_pos²))``
(``RansacOptions.map_rotation_std_deg``, ``map_position_std_m``), and the query pose is estimated
jointly with them. The corrections enter only the 2D-2D residuals of their own pair, so the
normal equations are solved by the Schur complement of the block-diagonal correction part
(Triggs, McLauchlan, Hartley & Fitzgibbon, "Bundle adjustment — a modern synthesis", 1999,
Sec. 6.1): per pair only 6x6 matrices. The returned normal matrix is that Schur complement, the
marginal information of the query pose, so ``σ̂² H⁻¹`` already holds the map's share of the
position uncertainty of the 2D-2D constraints. 2D-3D points are held fixed (their own
uncertainty is propagated separately, :func:`planarloc.robust.observability.points_covariance`).
Not in the paper.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.so3 import exp_so3
from planarloc.numerics.cholesky import solve_spd, spd_inverse
from planarloc.robust.problem import ProblemArrays, with_references
from planarloc.robust.refinement import (
    FASTMATH,
    Refinement,
    RefineSettings,
    StartPose,
    irls_normal_equations,
    residuals,
    residuals_jacobian,
)


@njit(cache=True, error_model="numpy", inline="always")
def _perturbed_refs(
    ref_R: np.ndarray,
    ref_c: np.ndarray,
    omega: np.ndarray,
    d: np.ndarray,
    B: np.ndarray,
    R_out: np.ndarray,
    t_out: np.ndarray,
) -> None:
    """``R_p' = Exp(ω_p) R_p``, ``t_p' = −R_p' (c_p + B d_p)`` for every pair."""
    for p in range(ref_R.shape[0]):
        Rp = m3.mul(exp_so3(omega[p]), ref_R[p])
        m3.store_pose(R_out, t_out, p, Rp, -m3.vec(Rp, ref_c[p] + m3.vec(B, d[p])))


@njit(cache=True, error_model="numpy")
def _prior_cost(omega: np.ndarray, d: np.ndarray, lam_rot: float, lam_pos: float) -> float:
    """``½ Σ_p δ_pᵀ Λ δ_p`` of the corrections ω (P, 3), d (P, 3)."""
    acc = 0.0
    for p in range(omega.shape[0]):
        for k in range(3):
            acc += lam_rot * omega[p, k] * omega[p, k] + lam_pos * d[p, k] * d[p, k]
    return 0.5 * acc


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _pair_blocks(
    J: np.ndarray,
    Jrot: np.ndarray,
    r: np.ndarray,
    rows_pair: np.ndarray,
    s2: float,
    fixed: np.ndarray,
    Bp: np.ndarray,
    Dp: np.ndarray,
    hp: np.ndarray,
) -> None:
    """Per pair, the IRLS blocks of the reference corrections' normal equations from the 2D-2D
    rows (pair ``rows_pair[i]`` of row i): ``B_p`` (query x reference), the upper triangle of
    ``D_p`` and the gradient ``h_p``. Zeroes the ``fixed`` query columns of J afterwards."""
    n2 = rows_pair.shape[0]
    Kr = np.empty((n2, 6))
    # Reference parameters' Jacobian before the fixed query columns are zeroed: a reference
    # centre moves in every direction (its shift acts as the opposite query shift).
    for i in range(n2):
        Kr[i, 0], Kr[i, 1], Kr[i, 2] = Jrot[i, 0], Jrot[i, 1], Jrot[i, 2]
        Kr[i, 3], Kr[i, 4], Kr[i, 5] = -J[i, 3], -J[i, 4], -J[i, 5]
    for k in range(6):
        if fixed[k]:
            J[:, k] = 0.0
    Bp[:] = 0.0
    Dp[:] = 0.0
    hp[:] = 0.0
    for i in range(n2):
        w = 1.0 / (1.0 + r[i] * r[i] / s2)
        q = rows_pair[i]
        for a in range(6):
            wk = w * Kr[i, a]
            hp[q, a] += wk * r[i]
            for b in range(6):
                Bp[q, b, a] += w * J[i, b] * Kr[i, a]
            for b in range(a, 6):
                Dp[q, a, b] += wk * Kr[i, b]


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _add_prior(
    Dp: np.ndarray, hp: np.ndarray, omega: np.ndarray, dvec: np.ndarray, lam_rot: float, lam_pos: float
) -> None:
    """Symmetrise ``D_p`` and add the prior's information and gradient at the corrections."""
    for p in range(Dp.shape[0]):
        for a in range(6):
            for b in range(a):
                Dp[p, a, b] = Dp[p, b, a]
        for k in range(3):
            Dp[p, k, k] += lam_rot
            Dp[p, 3 + k, 3 + k] += lam_pos
            hp[p, k] += lam_rot * omega[p, k]
            hp[p, 3 + k] += lam_pos * dvec[p, k]


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _marginal_information(
    H: np.ndarray, Bp: np.ndarray, Dp: np.ndarray, Hm: np.ndarray, Dinv: np.ndarray
) -> bool:
    """``Hm = H − Σ_p B_p D_p⁻¹ B_pᵀ`` (undamped Schur complement: the query's marginal
    information, symmetrised); False, Hm unfinished, when a ``D_p`` is not positive definite."""
    # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
    for a in range(H.shape[0]):
        for b in range(H.shape[1]):
            Hm[a, b] = H[a, b]
    P = Dp.shape[0]
    ok_all = True
    for p in range(P):
        ok_all = ok_all and spd_inverse(Dp[p], Dinv[p], 0.0)
    if not ok_all:
        return False
    for p in range(P):
        BD = np.empty((6, 6))
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for k in range(6):
                    acc += Bp[p, a, k] * Dinv[p, k, b]
                BD[a, b] = acc
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for k in range(6):
                    acc += BD[a, k] * Bp[p, b, k]
                Hm[a, b] -= acc
    for a in range(6):
        for b in range(a):
            v = 0.5 * (Hm[a, b] + Hm[b, a])
            Hm[a, b] = v
            Hm[b, a] = v
    return True


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _damped_query_step(
    H: np.ndarray,
    g: np.ndarray,
    blocks: tuple,
    lam: float,
    fixed: np.ndarray,
    Dinv: np.ndarray,
    step: np.ndarray,
) -> bool:
    """The query's LM step (damping ``lam``) with the references eliminated: solves
    ``(S + λ diag S) step = rhs``, ``S = H − Σ B D_λ⁻¹ Bᵀ``, ``rhs = −g + Σ B D_λ⁻¹ h`` for
    ``blocks = (B_p, D_p, h_p)``, leaving ``D_λ⁻¹`` in ``Dinv``; False if not solvable."""
    Bp, Dp, hp = blocks
    P = Dp.shape[0]
    S = H.copy()
    rhs = -g.copy()
    for k in range(6):
        S[k, k] += lam * max(H[k, k], 1e-12)
        if fixed[k]:
            S[k, k] = 1.0
    Dl = np.empty((P, 6, 6))
    for p in range(P):
        for a in range(6):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            for b in range(6):
                Dl[p, a, b] = Dp[p, a, b]
        for k in range(6):
            Dl[p, k, k] += lam * Dp[p, k, k]
        if not spd_inverse(Dl[p], Dinv[p], 0.0):
            return False
        # S -= B D⁻¹ Bᵀ, rhs += B D⁻¹ h
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for k in range(6):
                    for l2 in range(6):
                        acc += Bp[p, a, k] * Dinv[p, k, l2] * Bp[p, b, l2]
                S[a, b] -= acc
            acc = 0.0
            for k in range(6):
                for l2 in range(6):
                    acc += Bp[p, a, k] * Dinv[p, k, l2] * hp[p, l2]
            rhs[a] += acc
    return solve_spd(S, rhs, step)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _reference_corrections(
    blocks: tuple, Dinv: np.ndarray, step: np.ndarray, omega: np.ndarray, dvec: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The references' corrections after the query's ``step``: ``δ_p −= D_λ⁻¹ (h_p + B_pᵀ step)``,
    as new (ω (P, 3), d (P, 3)) arrays."""
    Bp, _, hp = blocks
    P = hp.shape[0]
    steps_p = np.zeros((P, 6))
    om_new = omega.copy()
    d_new = dvec.copy()
    for p in range(P):
        for a in range(6):
            acc = -hp[p, a]
            for k in range(6):
                acc -= Bp[p, k, a] * step[k]
            steps_p[p, a] = acc
        for a in range(6):
            acc = 0.0
            for k in range(6):
                acc += Dinv[p, a, k] * steps_p[p, k]
            if a < 3:
                om_new[p, a] += acc
            else:
                d_new[p, a - 3] += acc
    return om_new, d_new


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _prior_weights(r: np.ndarray, s2: float, settings: RefineSettings) -> tuple:
    """``(λ_rot, λ_pos) = σ̂² / (σ_rot², σ_pos²)`` of the settings' map prior, with σ̂ the IRLS
    residual scale at the initial residuals ``r`` (floored at ``settings.sigma_floor``)."""
    m = r.shape[0]
    wr2 = 0.0
    for i in range(m):
        wr2 += r[i] * r[i] / (1.0 + r[i] * r[i] / s2)
    sig2 = max(wr2 / max(m - 6, 1), settings.sigma_floor * settings.sigma_floor)
    return (
        sig2 / max(settings.map_rotation_std_rad, 1e-9) ** 2,
        sig2 / max(settings.map_position_std_m, 1e-9) ** 2,
    )


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def refine_with_map_prior(
    start: StartPose, prob: ProblemArrays, idx2d: np.ndarray, idx3d: np.ndarray, settings: RefineSettings
) -> Refinement:
    """Levenberg-Marquardt (IRLS, Cauchy loss at ``settings.loss_scale``) of the query pose and one
    pose correction per reference with the settings' map prior; same arguments and returns as
    :func:`planarloc.robust.refinement.refine_pose` (the centre ``c = start.c + start.B p``,
    ``start.fixed`` query parameters held), except that H is the Schur complement (marginal
    information of the query's 6 parameters) and the cost includes the prior. The prior's pixel
    scale is σ̂ at the initial pose (floored at ``settings.sigma_floor``):
    ``Λ = σ̂² diag(1/σ_rot², 1/σ_pos²)``. Reference centre shifts are expressed in the same
    orthonormal basis B (the prior is isotropic).
    """
    ref_R, ref_t, pair = prob.ref_R, prob.ref_t, prob.pair
    P = ref_R.shape[0]
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    R, c, B, fixed = start.R.copy(), start.c.copy(), start.B, start.fixed
    ref_c = np.empty((P, 3))
    for p in range(P):
        cp = m3.t_vec(ref_R[p], ref_t[p])
        for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            ref_c[p, a] = -cp[a]
    omega = np.zeros((P, 3))
    dvec = np.zeros((P, 3))
    cur_R, cur_t = ref_R.copy(), ref_t.copy()
    r = np.empty(m)
    rp = np.empty(m)
    J = np.empty((m, 6))
    Jrot = np.empty((m, 3))
    zero = np.zeros(6)
    s2 = settings.loss_scale * settings.loss_scale
    residuals_jacobian(R, c, B, with_references(prob, cur_R, cur_t), idx2d, idx3d, r, J, Jrot)
    lam_rot, lam_pos = _prior_weights(r, s2, settings)
    wr2 = 0.0
    cost = 0.5 * s2 * np.sum(np.log1p(r * r / s2)) + _prior_cost(omega, dvec, lam_rot, lam_pos)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    Bp = np.zeros((P, 6, 6))
    Dp = np.zeros((P, 6, 6))
    hp = np.zeros((P, 6))
    Hm = np.zeros((6, 6))
    lam = 1e-4
    rows_pair = pair[idx2d]
    Dinv = np.empty((P, 6, 6))
    max_iterations = settings.max_iterations
    for it in range(max_iterations + 1):
        _pair_blocks(J, Jrot, r, rows_pair, s2, fixed, Bp, Dp, hp)
        wr2 = irls_normal_equations(J, r, s2, H, g)
        _add_prior(Dp, hp, omega, dvec, lam_rot, lam_pos)
        if not _marginal_information(H, Bp, Dp, Hm, Dinv):
            break
        if it == max_iterations:
            break
        improved = False
        step = np.zeros(6)
        for _try in range(6):
            if not _damped_query_step(H, g, (Bp, Dp, hp), lam, fixed, Dinv, step):
                lam *= 10.0
                continue
            om_new, d_new = _reference_corrections((Bp, Dp, hp), Dinv, step, omega, dvec)
            R_new = m3.mul(exp_so3(step[:3]), R)
            c_new = c + m3.vec(B, step[3:])
            new_R, new_t = np.empty_like(ref_R), np.empty_like(ref_t)
            _perturbed_refs(ref_R, ref_c, om_new, d_new, B, new_R, new_t)
            residuals(zero, R_new, c_new, B, with_references(prob, new_R, new_t), idx2d, idx3d, rp)
            new_cost = 0.5 * s2 * np.sum(np.log1p(rp * rp / s2)) + _prior_cost(
                om_new, d_new, lam_rot, lam_pos
            )
            if new_cost <= cost:
                R, c, omega, dvec, cur_R, cur_t = R_new, c_new, om_new, d_new, new_R, new_t
                improved = cost - new_cost > max(1e-6 * cost, 5e-4 * wr2 / max(m - 6, 1))
                cost = new_cost
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        residuals_jacobian(R, c, B, with_references(prob, cur_R, cur_t), idx2d, idx3d, r, J, Jrot)
        if not improved or np.sqrt(np.sum(step * step)) < 1e-9:
            max_iterations = it + 1  # one more pass to evaluate H at the solution
    sigma2 = max(wr2 / max(m - 6, 1), settings.sigma_floor * settings.sigma_floor)
    return Refinement(R, -m3.vec(R, c), Hm, np.sqrt(sigma2), cost)
