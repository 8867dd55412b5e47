"""Robust 6DoF refinement of the query pose over all inliers (paper Sec. IV-B, last paragraph).

Minimises ``Σ ρ(r)`` with the Cauchy loss ``ρ(r) = σ²/2 · log(1 + r²/σ²)`` over the signed
Sampson errors (pixels) of the inlier 2D-2D matches and the reprojection errors (pixels,
2 per constraint) of the inlier 2D-3D constraints, by Levenberg-Marquardt with IRLS
weights. Parameters: a rotation increment ``δ`` (``R = Exp(δ) R₀``) and the camera
centre ``c`` directly, so that the position covariance is a block of the inverse normal
matrix: ``Σ_c = σ̂² (JᵀWJ)⁻¹[3:, 3:]``. Its largest eigenvalue gives ``position_std_m``;
with 2D-2D constraints only and the query collinear with the reference centres it blows up
(the scale along the line is unobservable), which is how degeneracy is detected.

The Jacobian is analytic (:func:`residuals_jacobian`); the map-uncertainty propagation
uses finite differences over the reference poses, once per query.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.epipolar_kernels import project, relative_essential_into, sampson_signed
from planarloc.geometry.so3 import exp_so3, exp_so3_into
from planarloc.numerics.cholesky import cholesky_factor, cholesky_solve, spd_inverse
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.scoring import errors_sq

# Floating-point contraction and reassociation for the Jacobian's sums of products, but not
# the no-NaN/no-inf assumptions (the kernels test for degenerate values).
FASTMATH = {"contract", "reassoc", "arcp", "nsz"}


class StartPose(NamedTuple):
    """Where a refinement starts and what it moves, as one record for the kernels: R (3, 3) the
    rotation of ``query_from_world`` and c (3,) the camera centre, parametrised as
    ``c + B p`` with B (3, 3) orthonormal, and fixed (6,) bool the parameters held at their start
    (rotation 0-2, centre 3-5; e.g. to profile the cost along one direction)."""

    R: np.ndarray
    c: np.ndarray
    B: np.ndarray
    fixed: np.ndarray


class RefineSettings(NamedTuple):
    """How a refinement runs, as one record for the kernels.

    Attributes:
        inlier_threshold_sq: τ² (pixels²): the kernels that choose their own rows refine on the
            data whose squared error at the start is below it.
        loss_scale: Cauchy scale σ in pixels.
        max_iterations: Levenberg-Marquardt iterations.
        sigma_floor: lower bound on σ̂ in pixels for the covariance, so that noise-free or
            overfitted residuals cannot make an ill-conditioned position look certain.
        map_rotation_std_rad, map_position_std_m: the map prior, the std of each map image's
            rotation (radians) and centre (metres) per axis, read by the refinements under it
            (:mod:`planarloc.robust.map_prior`); 0 and 0: none.
    """

    inlier_threshold_sq: float
    loss_scale: float
    max_iterations: int
    sigma_floor: float
    map_rotation_std_rad: float
    map_position_std_m: float


@njit(cache=True)
def with_iterations(settings: RefineSettings, max_iterations: int) -> RefineSettings:
    """``settings`` with another iteration budget."""
    return RefineSettings(
        settings.inlier_threshold_sq,
        settings.loss_scale,
        max_iterations,
        settings.sigma_floor,
        settings.map_rotation_std_rad,
        settings.map_position_std_m,
    )


class Refinement(NamedTuple):
    """A refined ``query_from_world``: R (3, 3), t (3,), the (6, 6) normal matrix ``JᵀWJ`` at the
    solution (:func:`centre_covariance`), the residual scale σ̂ (pixels) and the final robust cost."""

    R: np.ndarray
    t: np.ndarray
    H: np.ndarray
    sigma: float
    cost: float


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def residuals(
    params: np.ndarray,
    R0: np.ndarray,
    c0: np.ndarray,
    B: np.ndarray,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    idx3d: np.ndarray,
    out: np.ndarray,
) -> None:
    """Signed Sampson errors (pixels) of the 2D-2D rows ``idx2d``, then reprojection errors (2 per
    2D-3D row ``idx3d``) of the problem ``prob``, through the shared kernels of
    :mod:`planarloc.geometry.epipolar_kernels` (the same errors scoring thresholds)."""
    Rq = m3.mul(exp_so3(params[:3]), R0)
    c = c0 + m3.vec(B, params[3:])
    _residuals_at(Rq, c, prob, idx2d, idx3d, out, np.empty((prob.ref_R.shape[0], 3, 3)), np.empty(3))


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _residuals_at(
    Rq: np.ndarray,
    c: np.ndarray,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    idx3d: np.ndarray,
    out: np.ndarray,
    Es: np.ndarray,
    tq: np.ndarray,
) -> None:
    """The errors of :func:`residuals` at the pose ``(Rq, c)`` itself (no increment), with its
    essential matrices in the scratch ``Es`` (P, 3, 3) and ``tq`` (3,): the trial steps of
    :func:`refine_pose_core` call it with scratch they allocate once."""
    xq, xr, pair, f_query, f_ref = prob.xq, prob.xr, prob.pair, prob.f_query, prob.f_ref
    ref_R, ref_t, xq3d, X3d = prob.ref_R, prob.ref_t, prob.xq3d, prob.X3d
    for i in range(3):
        tq[i] = -(Rq[i, 0] * c[0] + Rq[i, 1] * c[1] + Rq[i, 2] * c[2])
    for p in range(ref_R.shape[0]):
        relative_essential_into(ref_R[p], ref_t[p], Rq, tq, Es[p])
    fq0, fq1 = f_query[0], f_query[1]
    for n in range(idx2d.shape[0]):
        i = idx2d[n]
        p = pair[i]
        out[n] = sampson_signed(Es[p], xq[i], xr[i], fq0, fq1, f_ref[p, 0], f_ref[p, 1])
    m0 = idx2d.shape[0]
    f30, f31 = f_query[2], f_query[3]
    for n in range(idx3d.shape[0]):
        i = idx3d[n]
        u, v, _ = project(Rq, tq, X3d[i])
        out[m0 + 2 * n] = (u - xq3d[i, 0] / xq3d[i, 2]) * f30
        out[m0 + 2 * n + 1] = (v - xq3d[i, 1] / xq3d[i, 2]) * f31


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _essential_derivatives(
    R: np.ndarray, c: np.ndarray, B: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per pair p, ``E_p = [t]x R_pq`` (P, 3, 3) of the query ``(R, c)`` and ``D_p`` (P, 9, 6), the
    derivatives of its entries w.r.t. ``(δ, p)`` (:func:`residuals_jacobian`)."""
    P = ref_R.shape[0]
    E = np.empty((P, 3, 3))
    D = np.empty((P, 9, 6))  # D[p, 3 i + j, k] = ∂E_ij / ∂param_k
    for p in range(P):
        A = m3.mul_t(ref_R[p], R)  # R_pq
        t = ref_t[p] + m3.vec(ref_R[p], c)
        for j in range(3):
            E[p, 0, j] = -t[2] * A[1, j] + t[1] * A[2, j]
            E[p, 1, j] = t[2] * A[0, j] - t[0] * A[2, j]
            E[p, 2, j] = -t[1] * A[0, j] + t[0] * A[1, j]
        for i in range(3):
            # rotation: ∂E/∂δ_k = −E [e_k]x, row i
            D[p, 3 * i, 0], D[p, 3 * i + 1, 0], D[p, 3 * i + 2, 0] = 0.0, -E[p, i, 2], E[p, i, 1]
            D[p, 3 * i, 1], D[p, 3 * i + 1, 1], D[p, 3 * i + 2, 1] = E[p, i, 2], 0.0, -E[p, i, 0]
            D[p, 3 * i, 2], D[p, 3 * i + 1, 2], D[p, 3 * i + 2, 2] = -E[p, i, 1], E[p, i, 0], 0.0
        for k in range(3):
            # centre: [v]x R_pq with v = R_p b_k
            v0 = ref_R[p, 0, 0] * B[0, k] + ref_R[p, 0, 1] * B[1, k] + ref_R[p, 0, 2] * B[2, k]
            v1 = ref_R[p, 1, 0] * B[0, k] + ref_R[p, 1, 1] * B[1, k] + ref_R[p, 1, 2] * B[2, k]
            v2 = ref_R[p, 2, 0] * B[0, k] + ref_R[p, 2, 1] * B[1, k] + ref_R[p, 2, 2] * B[2, k]
            for j in range(3):
                D[p, j, 3 + k] = -v2 * A[1, j] + v1 * A[2, j]
                D[p, 3 + j, 3 + k] = v2 * A[0, j] - v0 * A[2, j]
                D[p, 6 + j, 3 + k] = -v1 * A[0, j] + v0 * A[1, j]
    return E, D


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _sampson_rows(
    E: np.ndarray,
    D: np.ndarray,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    r: np.ndarray,
    J: np.ndarray,
    Jrot: np.ndarray,
) -> None:
    """The 2D-2D rows of :func:`residuals_jacobian`: Sampson residuals, their Jacobian chained
    through ``D`` and, when ``Jrot`` is not empty, their reference-rotation derivatives."""
    xq, xr, pair, f_query, f_ref = prob.xq, prob.xr, prob.pair, prob.f_query, prob.f_ref
    P = E.shape[0]
    want_ref = Jrot.shape[0] > 0
    fq0, fq1 = f_query[0], f_query[1]
    iq0, iq1 = 1.0 / (fq0 * fq0), 1.0 / (fq1 * fq1)
    ir = np.empty((P, 2))
    for p in range(P):
        ir[p, 0], ir[p, 1] = 1.0 / (f_ref[p, 0] * f_ref[p, 0]), 1.0 / (f_ref[p, 1] * f_ref[p, 1])
    for n in range(idx2d.shape[0]):
        i = idx2d[n]
        p = pair[i]
        q0, q1, q2 = xq[i, 0], xq[i, 1], xq[i, 2]
        r0, r1, r2 = xr[i, 0], xr[i, 1], xr[i, 2]
        Ex0 = E[p, 0, 0] * q0 + E[p, 0, 1] * q1 + E[p, 0, 2] * q2
        Ex1 = E[p, 1, 0] * q0 + E[p, 1, 1] * q1 + E[p, 1, 2] * q2
        Ex2 = E[p, 2, 0] * q0 + E[p, 2, 1] * q1 + E[p, 2, 2] * q2
        Et0 = E[p, 0, 0] * r0 + E[p, 1, 0] * r1 + E[p, 2, 0] * r2
        Et1 = E[p, 0, 1] * r0 + E[p, 1, 1] * r1 + E[p, 2, 1] * r2
        ir0, ir1 = ir[p, 0], ir[p, 1]
        res = r0 * Ex0 + r1 * Ex1 + r2 * Ex2
        den = max(Ex0 * Ex0 * ir0 + Ex1 * Ex1 * ir1 + Et0 * Et0 * iq0 + Et1 * Et1 * iq1, 1e-300)
        isq = 1.0 / np.sqrt(den)
        r[n] = res * isq
        # ∂s/∂E_ij = isq r_i q_j − h (∂den/∂E_ij), h = ½ res / den^{3/2}, with
        # ∂den/∂E_ij = 2 (Ex0 ir0 [i=0] + Ex1 ir1 [i=1]) q_j + 2 r_i (Et0 iq0 [j=0] + Et1 iq1 [j=1])
        h2 = res * isq * isq * isq  # 2h
        a0 = isq * r0 - h2 * Ex0 * ir0
        a1 = isq * r1 - h2 * Ex1 * ir1
        a2 = isq * r2
        b0 = h2 * Et0 * iq0
        b1 = h2 * Et1 * iq1
        g00, g01, g02 = a0 * q0 - r0 * b0, a0 * q1 - r0 * b1, a0 * q2
        g10, g11, g12 = a1 * q0 - r1 * b0, a1 * q1 - r1 * b1, a1 * q2
        g20, g21, g22 = a2 * q0 - r2 * b0, a2 * q1 - r2 * b1, a2 * q2
        Dp = D[p]
        for k in range(6):
            J[n, k] = (
                g00 * Dp[0, k]
                + g01 * Dp[1, k]
                + g02 * Dp[2, k]
                + g10 * Dp[3, k]
                + g11 * Dp[4, k]
                + g12 * Dp[5, k]
                + g20 * Dp[6, k]
                + g21 * Dp[7, k]
                + g22 * Dp[8, k]
            )
        if want_ref:
            e0, e1, e2 = E[p, 0], E[p, 1], E[p, 2]
            Jrot[n, 0] = -(g10 * e2[0] + g11 * e2[1] + g12 * e2[2]) + (
                g20 * e1[0] + g21 * e1[1] + g22 * e1[2]
            )
            Jrot[n, 1] = (g00 * e2[0] + g01 * e2[1] + g02 * e2[2]) - (g20 * e0[0] + g21 * e0[1] + g22 * e0[2])
            Jrot[n, 2] = -(g00 * e1[0] + g01 * e1[1] + g02 * e1[2]) + (
                g10 * e0[0] + g11 * e0[1] + g12 * e0[2]
            )


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _reprojection_rows(
    R: np.ndarray,
    c: np.ndarray,
    B: np.ndarray,
    prob: ProblemArrays,
    m0: int,
    idx3d: np.ndarray,
    r: np.ndarray,
    J: np.ndarray,
    Jrot: np.ndarray,
) -> None:
    """The 2D-3D rows of :func:`residuals_jacobian` (from row ``m0``): reprojection residuals and
    their Jacobian; 0 in ``Jrot`` when it is not empty."""
    xq3d, X3d, f_query = prob.xq3d, prob.X3d, prob.f_query
    want_ref = Jrot.shape[0] > 0
    RB = m3.mul(R, B)
    fq0, fq1 = f_query[2], f_query[3]  # reprojection errors' scale (AbsolutePoseProblem.f_query)
    for n in range(idx3d.shape[0]):
        i = idx3d[n]
        D0, D1, D2 = X3d[i, 0] - c[0], X3d[i, 1] - c[1], X3d[i, 2] - c[2]
        X0 = R[0, 0] * D0 + R[0, 1] * D1 + R[0, 2] * D2
        X1 = R[1, 0] * D0 + R[1, 1] * D1 + R[1, 2] * D2
        X2 = R[2, 0] * D0 + R[2, 1] * D1 + R[2, 2] * D2
        z = max(X2, 1e-6)
        u, v = X0 / z, X1 / z
        r[m0 + 2 * n] = (u - xq3d[i, 0] / xq3d[i, 2]) * fq0
        r[m0 + 2 * n + 1] = (v - xq3d[i, 1] / xq3d[i, 2]) * fq1
        if want_ref:
            Jrot[m0 + 2 * n, :] = 0.0
            Jrot[m0 + 2 * n + 1, :] = 0.0
        for k in range(6):
            if k == 0:
                g0, g1, g2 = 0.0, -X2, X1
            elif k == 1:
                g0, g1, g2 = X2, 0.0, -X0
            elif k == 2:
                g0, g1, g2 = -X1, X0, 0.0
            else:
                g0, g1, g2 = -RB[0, k - 3], -RB[1, k - 3], -RB[2, k - 3]
            J[m0 + 2 * n, k] = (g0 - u * g2) / z * fq0
            J[m0 + 2 * n + 1, k] = (g1 - v * g2) / z * fq1


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def residuals_jacobian(
    R: np.ndarray,
    c: np.ndarray,
    B: np.ndarray,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    idx3d: np.ndarray,
    r: np.ndarray,
    J: np.ndarray,
    Jrot: np.ndarray,
) -> None:
    """Residuals and their analytic Jacobian w.r.t. ``(δ, p)`` at ``δ = 0, p = 0`` for the query
    ``R' = Exp(δ) R``, ``c' = c + B p``.

    With ``p_from_query = (R_p Rᵀ, t_p + R_p c)`` and ``E = [t]x R_pq``:
    ``∂E/∂δ_k = −E [e_k]x`` and ``∂E/∂p_k = [R_p b_k]x R_pq``, gathered once per pair into
    ``D_p`` (9, 6). Per match, the Sampson residual ``s = rᵀEq / √den`` is differentiated w.r.t.
    the 9 entries of E (``∂s/∂E_ij = α_i q_j − r_i β_j``, see the code) and chained with
    ``D_p``: ~90 flops per match instead of differentiating through each parameter (~200).
    Reprojection: ``X_c = R (X − c)``, ``∂X_c/∂δ_k = e_k × X_c``, ``∂X_c/∂p_k = −R b_k``.

    ``Jrot`` (m, 3), unless empty: derivatives of each 2D-2D residual w.r.t. a rotation increment
    ``ω`` of its own reference, ``R_p' = Exp(ω) R_p`` with the reference centre fixed, for the
    map-uncertainty propagation: then ``E' = Exp(ω) E`` (as ``[Rv]x R = R [v]x``), so
    ``∂E/∂ω_k = [e_k]x E``. (A shift of the reference centre acts as the opposite shift of the
    query centre.) 2D-3D rows get 0.
    """
    E, D = _essential_derivatives(R, c, B, prob.ref_R, prob.ref_t)
    _sampson_rows(E, D, prob, idx2d, r, J, Jrot)
    _reprojection_rows(R, c, B, prob, idx2d.shape[0], idx3d, r, J, Jrot)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def irls_normal_equations(J: np.ndarray, r: np.ndarray, s2: float, H: np.ndarray, g: np.ndarray) -> float:
    """``H = Jᵀ W J`` (6, 6) and ``g = Jᵀ W r`` (6,) in place, with the Cauchy IRLS weights
    ``w = 1 / (1 + r² / s²)`` of residuals r (m,) and Jacobian J (m, 6); returns ``Σ w r²``."""
    H[:] = 0.0
    g[:] = 0.0
    wr2 = 0.0
    for i in range(r.shape[0]):
        w = 1.0 / (1.0 + r[i] * r[i] / s2)
        wr2 += w * r[i] * r[i]
        for a in range(6):
            wa = w * J[i, a]
            g[a] += wa * r[i]
            for b in range(a, 6):
                H[a, b] += wa * J[i, b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return wr2


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def refine_pose_core(
    start: StartPose,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    idx3d: np.ndarray,
    settings: RefineSettings,
    final_normal: np.bool_,
) -> Refinement:
    """Refine ``query_from_world`` on the given inliers.

    Args:
        start: the initial pose and its parametrisation (:class:`StartPose`).
        prob: the problem's arrays (:attr:`planarloc.robust.problem.AbsolutePoseProblem.arrays`).
        idx2d: (K,) rows of inlier 2D-2D matches; idx3d: (L,) rows of inlier 2D-3D constraints.
        settings: the loss scale, iterations and σ̂ floor (:class:`RefineSettings`; its
            inlier threshold and map prior are not read here).
        final_normal: False: the normal matrix and σ̂ are not re-evaluated after the last step
            (stale), which saves one residual-and-Jacobian pass where only the pose is wanted
            (leave-one-out refinements); :func:`refine_pose` passes True.

    Returns:
        R (3, 3), t (3,), the (6, 6) normal matrix ``JᵀWJ`` at the solution (parameters
        ``(δ, p)``; see :func:`centre_covariance`), the residual scale σ̂ in pixels, and the
        final robust cost.
    """
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    R, c, B, fixed = start.R.copy(), start.c.copy(), start.B, start.fixed
    r = np.empty(m)
    rp = np.empty(m)
    J = np.empty((m, 6))
    H = np.empty((6, 6))
    g = np.empty(6)
    # The trial steps' scratch, allocated once.
    A, L, neg_g, step = np.empty((6, 6)), np.empty((6, 6)), np.empty(6), np.zeros(6)
    Exp, R_new, c_new = np.empty((3, 3)), np.empty((3, 3)), np.empty(3)
    Es, tq = np.empty((prob.ref_R.shape[0], 3, 3)), np.empty(3)
    s2 = settings.loss_scale * settings.loss_scale
    lam = 1e-4
    no_ref = np.empty((0, 3))
    residuals_jacobian(R, c, B, prob, idx2d, idx3d, r, J, no_ref)
    cost = 0.5 * s2 * np.sum(np.log1p(r * r / s2))
    wr2 = 0.0
    max_iterations = settings.max_iterations
    for it in range(max_iterations + 1):
        for k in range(6):
            if fixed[k]:
                J[:, k] = 0.0
        wr2 = irls_normal_equations(J, r, s2, H, g)
        if it == max_iterations:
            break
        improved = False
        for k in range(6):
            step[k] = 0.0
            neg_g[k] = -g[k]
        for _try in range(6):
            for a in range(6):
                for b in range(6):
                    A[a, b] = H[a, b]
            for k in range(6):
                A[k, k] += lam * max(H[k, k], 1e-12)
                if fixed[k]:
                    A[k, k] = 1.0
            if not cholesky_factor(A, L, 0.0):
                lam *= 10.0
                continue
            cholesky_solve(L, neg_g, step)
            exp_so3_into(step, Exp)
            m3.mul_into(Exp, R, R_new)
            for k in range(3):
                c_new[k] = c[k] + (B[k, 0] * step[3] + B[k, 1] * step[4] + B[k, 2] * step[5])
            _residuals_at(R_new, c_new, prob, idx2d, idx3d, rp, Es, tq)
            new_cost = 0.5 * s2 * np.sum(np.log1p(rp * rp / s2))
            if new_cost <= cost:
                R, R_new = R_new, R
                c, c_new = c_new, c
                # Converged when a step gains less than 5e-4 σ̂² of cost: with the quadratic
                # model ΔC ≈ ½ (δ/std)² σ̂², the step moved the pose by < ~0.03 std, and IRLS
                # contracts the remaining error ~4× per iteration (1e-6 of the cost alone took
                # 5-6 iterations on 200 inliers for changes of 1e-3 std).
                improved = cost - new_cost > max(1e-6 * cost, 5e-4 * wr2 / max(m - 6, 1))
                cost = new_cost
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        if not final_normal and it == max_iterations - 1:
            break  # the pose is what the caller wants; H and σ̂ stay those of the last pass
        if improved or _try < 6:
            residuals_jacobian(R, c, B, prob, idx2d, idx3d, r, J, no_ref)
        if not improved or np.sqrt(np.sum(step * step)) < 1e-9:
            max_iterations = it + 1  # one more pass to evaluate H at the solution
    # The normal matrix JᵀWJ at the solution; the covariance σ̂² (JᵀWJ)⁻¹ is formed by the caller.
    dof = max(m - 6, 1)
    sigma2 = max(wr2 / dof, settings.sigma_floor * settings.sigma_floor)
    t = -m3.vec(R, c)
    return Refinement(R, t, H.copy(), np.sqrt(sigma2), cost)


#: :func:`refine_pose_core` with the normal matrix and σ̂ evaluated at the solution: the call of
#: every refinement that reports a covariance (same arguments but ``final_normal``).
refine_pose = functools.partial(refine_pose_core, final_normal=np.bool_(True))


@njit(cache=True, error_model="numpy")
def refine_on_inliers(
    Rq: np.ndarray, tq: np.ndarray, prob: ProblemArrays, settings: RefineSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, np.ndarray, np.ndarray]:
    """:func:`refine_pose` on the inliers of the initial pose, in one call.

    The inliers are the 2D-2D matches (Sampson) and 2D-3D constraints (reprojection) whose
    squared pixel error at ``(Rq, tq)`` is below ``settings.inlier_threshold_sq``; with fewer
    than 6 of them the pose is returned unchanged (cost inf).

    Returns:
        R, t, the normal matrix H, σ̂, cost (as :func:`refine_pose`), and the inlier masks
        (N,), (M,) bool at the initial pose.
    """
    e2d, e3d = errors_sq(Rq, tq, prob)
    in2d = e2d < settings.inlier_threshold_sq
    in3d = e3d < settings.inlier_threshold_sq
    idx2d = np.flatnonzero(in2d)
    idx3d = np.flatnonzero(in3d)
    if idx2d.shape[0] + idx3d.shape[0] < 6:
        return Rq.copy(), tq.copy(), np.zeros((6, 6)), np.inf, np.inf, in2d, in3d
    start = StartPose(Rq, -m3.t_vec(Rq, tq), np.eye(3), np.zeros(6, dtype=np.bool_))
    R, t, H, sigma, cost = refine_pose_core(start, prob, idx2d, idx3d, settings, np.bool_(True))
    return R, t, H, sigma, cost, in2d, in3d


@njit(cache=True, error_model="numpy")
def map_uncertainty_covariance(
    Rq: np.ndarray,
    tq: np.ndarray,
    prob: ProblemArrays,
    idx2d: np.ndarray,
    idx3d: np.ndarray,
    loss_scale: float,
    rotation_std_rad: float,
    position_std_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covariance of the query centre caused by errors of the map's reference poses.

    First-order propagation: with ``J`` the residual Jacobian w.r.t. the query parameters and
    ``J_r`` w.r.t. every reference pose (rotation increment and centre of each), the refined
    query moves by ``B δ_ref`` with ``B = (JᵀWJ)⁻¹ JᵀW J_r``, so
    ``Σ = B diag(σ_rot², σ_pos²) Bᵀ``. The 2D-3D constraints' points are held fixed (their
    triangulation error is part of the pixel noise). Map errors are systematic — every match
    of a pair sees the same error — so, unlike pixel noise, they do not average out over
    matches; near-collinear geometry amplifies them along the line of travel.

    Returns:
        ``H = JᵀWJ`` (6, 6), ``M = JᵀW J_r`` (6, 6P) and the variances (6P,) of the reference
        parameters; :func:`map_centre_covariance` forms the centre covariance (with a
        hand-written Cholesky: numba's LAPACK bindings are slow to compile).
    """
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    c0 = -m3.t_vec(Rq, tq)
    r = np.empty(m)
    J = np.empty((m, 6))
    Jrot = np.empty((m, 3))
    residuals_jacobian(Rq, c0, np.eye(3), prob, idx2d, idx3d, r, J, Jrot)
    pair = prob.pair
    s2 = loss_scale * loss_scale
    P = prob.ref_R.shape[0]
    H = np.zeros((6, 6))
    M = np.zeros((6, 6 * P))
    for n in range(m):
        w = 1.0 / (1.0 + r[n] * r[n] / s2)
        for a in range(6):
            wa = w * J[n, a]
            for b in range(6):
                H[a, b] += wa * J[n, b]
            if n < idx2d.shape[0]:  # a reference pose only moves its own pair's residuals
                col = 6 * pair[idx2d[n]]
                for k in range(3):
                    M[a, col + k] += wa * Jrot[n, k]
                    M[a, col + 3 + k] -= wa * J[n, 3 + k]  # reference centre shift = opposite query shift
    var = np.empty(6 * P)
    for p in range(P):
        for k in range(6):
            var[6 * p + k] = rotation_std_rad**2 if k < 3 else position_std_m**2
    return H, M, var


_EYE3 = np.eye(3)


@njit(cache=True, error_model="numpy")
def map_centre_covariance(H: np.ndarray, M: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of the query centre from the map's pose errors: the parts of
    :func:`map_uncertainty_covariance` combined as ``B diag(var) Bᵀ`` with ``B = H⁻¹ M`` (centre
    block), H factored once by Cholesky. Inf-filled when H is singular relative to its scale
    (pivot below 1e-12 of its largest diagonal entry)."""
    Hi = np.empty((6, 6))
    out = np.full((3, 3), np.inf)
    if not spd_inverse(H, Hi, 1e-12):
        return out
    Bc = (Hi @ M)[3:]  # (3, 6P): the centre's response to each reference parameter
    return (Bc * var) @ Bc.T


@njit(cache=True, error_model="numpy")
def _centre_covariance(H: np.ndarray, sigma: float, B: np.ndarray) -> np.ndarray:
    Hi = np.empty((6, 6))
    out = np.full((3, 3), np.inf)
    if not spd_inverse(H, Hi, 1e-12):
        return out
    s2 = sigma * sigma
    for a in range(3):
        for b in range(3):
            acc = 0.0
            for u in range(3):
                for v in range(3):
                    acc += B[a, u] * 0.5 * (Hi[3 + u, 3 + v] + Hi[3 + v, 3 + u]) * B[b, v]
            out[a, b] = s2 * acc
    return out


def centre_covariance(H: np.ndarray, sigma: float, B: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) covariance of the camera centre ``σ̂² B (H⁻¹)[3:, 3:] Bᵀ`` from the normal matrix.

    Inf-filled when H is singular relative to its scale (an unobservable direction): a
    Cholesky pivot below 1e-12 of H's largest diagonal entry. Compiled: it runs once per
    search and a LAPACK ``eigh`` from Python cost ~20 µs for this 6x6 matrix.
    """
    return _centre_covariance(
        np.ascontiguousarray(H, dtype=float),
        float(sigma),
        _EYE3 if B is None else np.ascontiguousarray(B, dtype=float),
    )
