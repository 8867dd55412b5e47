"""Robust 6DoF refinement of the query pose over all inliers (paper Sec. IV-B, last paragraph).

Minimises ``Σ ρ(r)`` with the Cauchy loss ``ρ(r) = σ²/2 · log(1 + r²/σ²)`` over the signed
Sampson errors (pixels) of the inlier 2D-2D matches and the reprojection errors (pixels,
2 per constraint) of the inlier 2D-3D constraints, by Levenberg-Marquardt with IRLS
weights. Parameters: a rotation increment ``δ`` (``R = Exp(δ) R₀``) and the camera
centre ``c`` directly, so that the position covariance is a block of the inverse normal
matrix: ``Σ_c = σ̂² (JᵀWJ)⁻¹[3:, 3:]``. Its largest eigenvalue gives ``position_std_m``;
with 2D-2D constraints only and the query collinear with the reference centres it blows up
(the scale along the line is unobservable), which is how degeneracy is detected.

The Jacobian is analytic (:func:`_residuals_jacobian`); the map-uncertainty propagation
uses finite differences over the reference poses, once per query.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.robust.scoring import _relative_essential, errors_sq


@njit(cache=True, error_model="numpy")
def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / (th * th) * m3.mul(K, K)


@njit(cache=True, error_model="numpy")
def _residuals(
    params: np.ndarray, R0: np.ndarray, c0: np.ndarray, B: np.ndarray, xq: np.ndarray, xr: np.ndarray,
    pair: np.ndarray, idx2d: np.ndarray, f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray,
    ref_t: np.ndarray, xq3d: np.ndarray, X3d: np.ndarray, idx3d: np.ndarray, out: np.ndarray,
) -> None:
    """Signed Sampson errors (pixels) of the 2D-2D rows, then reprojection errors (2 per 2D-3D row).

    Scalar code without array views in the loops: this runs ~10⁵ times per query.
    """
    Rq = m3.mul(_exp_so3(params[:3]), R0)
    c = c0 + m3.vec(B, params[3:])
    tq = -m3.vec(Rq, c)
    P = ref_R.shape[0]
    Es = np.empty((P, 3, 3))
    for p in range(P):
        _relative_essential(ref_R[p], ref_t[p], Rq, tq, Es[p])
    fq0, fq1 = f_query[0], f_query[1]
    for n in range(idx2d.shape[0]):
        i = idx2d[n]
        p = pair[i]
        q0, q1, q2 = xq[i, 0], xq[i, 1], xq[i, 2]
        r0, r1, r2 = xr[i, 0], xr[i, 1], xr[i, 2]
        Ex0 = Es[p, 0, 0] * q0 + Es[p, 0, 1] * q1 + Es[p, 0, 2] * q2
        Ex1 = Es[p, 1, 0] * q0 + Es[p, 1, 1] * q1 + Es[p, 1, 2] * q2
        Ex2 = Es[p, 2, 0] * q0 + Es[p, 2, 1] * q1 + Es[p, 2, 2] * q2
        Etx0 = Es[p, 0, 0] * r0 + Es[p, 1, 0] * r1 + Es[p, 2, 0] * r2
        Etx1 = Es[p, 0, 1] * r0 + Es[p, 1, 1] * r1 + Es[p, 2, 1] * r2
        res = r0 * Ex0 + r1 * Ex1 + r2 * Ex2
        a = Ex0 / f_ref[p, 0]
        b = Ex1 / f_ref[p, 1]
        den = a * a + b * b + (Etx0 / fq0) ** 2 + (Etx1 / fq1) ** 2
        out[n] = res / np.sqrt(max(den, 1e-300))
    m0 = idx2d.shape[0]
    for n in range(idx3d.shape[0]):
        i = idx3d[n]
        X0, X1, X2 = X3d[i, 0], X3d[i, 1], X3d[i, 2]
        z = max(Rq[2, 0] * X0 + Rq[2, 1] * X1 + Rq[2, 2] * X2 + tq[2], 1e-6)
        u = (Rq[0, 0] * X0 + Rq[0, 1] * X1 + Rq[0, 2] * X2 + tq[0]) / z
        v = (Rq[1, 0] * X0 + Rq[1, 1] * X1 + Rq[1, 2] * X2 + tq[1]) / z
        out[m0 + 2 * n] = (u - xq3d[i, 0] / xq3d[i, 2]) * fq0
        out[m0 + 2 * n + 1] = (v - xq3d[i, 1] / xq3d[i, 2]) * fq1


@njit(cache=True, error_model="numpy")
def _residuals_jacobian(
    R: np.ndarray, c: np.ndarray, B: np.ndarray, xq: np.ndarray, xr: np.ndarray, pair: np.ndarray,
    idx2d: np.ndarray, f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray,
    xq3d: np.ndarray, X3d: np.ndarray, idx3d: np.ndarray, r: np.ndarray, J: np.ndarray,
) -> None:
    """Residuals and their analytic Jacobian w.r.t. ``(δ, p)`` at ``δ = 0, p = 0`` for the query
    ``R' = Exp(δ) R``, ``c' = c + B p``.

    With ``p_from_query = (R_p Rᵀ, t_p + R_p c)`` and ``E = [t]x R_pq``:
    ``∂E/∂δ_k = −E [e_k]x`` and ``∂E/∂p_k = [R_p b_k]x R_pq``; the Sampson residual
    ``res / √den`` is differentiated by the quotient rule. Reprojection: ``X_c = R (X − c)``,
    ``∂X_c/∂δ_k = e_k × X_c``, ``∂X_c/∂p_k = −R b_k``.
    """
    P = ref_R.shape[0]
    E = np.empty((P, 3, 3))
    Rpq = np.empty((P, 3, 3))
    V = np.empty((P, 3, 3))  # V[p, k] = R_p b_k
    for p in range(P):
        Rpq[p] = m3.mul_t(ref_R[p], R)
        t = ref_t[p] + m3.vec(ref_R[p], c)
        for j in range(3):
            E[p, 0, j] = -t[2] * Rpq[p, 1, j] + t[1] * Rpq[p, 2, j]
            E[p, 1, j] = t[2] * Rpq[p, 0, j] - t[0] * Rpq[p, 2, j]
            E[p, 2, j] = -t[1] * Rpq[p, 0, j] + t[0] * Rpq[p, 1, j]
        for k in range(3):
            for j in range(3):
                V[p, k, j] = ref_R[p, j, 0] * B[0, k] + ref_R[p, j, 1] * B[1, k] + ref_R[p, j, 2] * B[2, k]
    fq0, fq1 = f_query[0], f_query[1]
    iq0, iq1 = 1.0 / (fq0 * fq0), 1.0 / (fq1 * fq1)
    for n in range(idx2d.shape[0]):
        i = idx2d[n]
        p = pair[i]
        q0, q1, q2 = xq[i, 0], xq[i, 1], xq[i, 2]
        r0, r1, r2 = xr[i, 0], xr[i, 1], xr[i, 2]
        e = E[p]
        Ex0 = e[0, 0] * q0 + e[0, 1] * q1 + e[0, 2] * q2
        Ex1 = e[1, 0] * q0 + e[1, 1] * q1 + e[1, 2] * q2
        Ex2 = e[2, 0] * q0 + e[2, 1] * q1 + e[2, 2] * q2
        Et0 = e[0, 0] * r0 + e[1, 0] * r1 + e[2, 0] * r2
        Et1 = e[0, 1] * r0 + e[1, 1] * r1 + e[2, 1] * r2
        Et2 = e[0, 2] * r0 + e[1, 2] * r1 + e[2, 2] * r2
        ir0, ir1 = 1.0 / (f_ref[p, 0] ** 2), 1.0 / (f_ref[p, 1] ** 2)
        res = r0 * Ex0 + r1 * Ex1 + r2 * Ex2
        den = max(Ex0 * Ex0 * ir0 + Ex1 * Ex1 * ir1 + Et0 * Et0 * iq0 + Et1 * Et1 * iq1, 1e-300)
        sq = np.sqrt(den)
        r[n] = res / sq
        # rotation: dEx = -E (e_k x q), dEtx = e_k x Etx
        for k in range(3):
            if k == 0:
                w0, w1, w2 = 0.0, -q2, q1
                d0, d1 = 0.0, -Et2
            elif k == 1:
                w0, w1, w2 = q2, 0.0, -q0
                d0, d1 = Et2, 0.0
            else:
                w0, w1, w2 = -q1, q0, 0.0
                d0, d1 = -Et1, Et0
            dx0 = -(e[0, 0] * w0 + e[0, 1] * w1 + e[0, 2] * w2)
            dx1 = -(e[1, 0] * w0 + e[1, 1] * w1 + e[1, 2] * w2)
            dx2 = -(e[2, 0] * w0 + e[2, 1] * w1 + e[2, 2] * w2)
            dres = r0 * dx0 + r1 * dx1 + r2 * dx2
            dden = 2.0 * (Ex0 * dx0 * ir0 + Ex1 * dx1 * ir1 + Et0 * d0 * iq0 + Et1 * d1 * iq1)
            J[n, k] = dres / sq - 0.5 * res * dden / (den * sq)
        # centre: dE = [v]x Rpq: dEx = v x (Rpq q), dEtx = Rpqᵀ (r x v)
        a = Rpq[p]
        y0 = a[0, 0] * q0 + a[0, 1] * q1 + a[0, 2] * q2
        y1 = a[1, 0] * q0 + a[1, 1] * q1 + a[1, 2] * q2
        y2 = a[2, 0] * q0 + a[2, 1] * q1 + a[2, 2] * q2
        for k in range(3):
            v0, v1, v2 = V[p, k, 0], V[p, k, 1], V[p, k, 2]
            dx0 = v1 * y2 - v2 * y1
            dx1 = v2 * y0 - v0 * y2
            dx2 = v0 * y1 - v1 * y0
            z0 = r1 * v2 - r2 * v1
            z1 = r2 * v0 - r0 * v2
            z2 = r0 * v1 - r1 * v0
            d0 = a[0, 0] * z0 + a[1, 0] * z1 + a[2, 0] * z2
            d1 = a[0, 1] * z0 + a[1, 1] * z1 + a[2, 1] * z2
            dres = r0 * dx0 + r1 * dx1 + r2 * dx2
            dden = 2.0 * (Ex0 * dx0 * ir0 + Ex1 * dx1 * ir1 + Et0 * d0 * iq0 + Et1 * d1 * iq1)
            J[n, 3 + k] = dres / sq - 0.5 * res * dden / (den * sq)
    m0 = idx2d.shape[0]
    RB = m3.mul(R, B)
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


@njit(cache=True, error_model="numpy")
def _solve_spd(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> bool:
    """Solve ``A x = b`` for a small symmetric positive-definite A by Cholesky; False if not SPD.

    Hand-written: numba's ``np.linalg.solve`` pulls in LAPACK bindings that take tens of
    seconds to compile, for a 6x6 system that this solves in ~100 ns.
    """
    n = A.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > 0.0:
                    return False
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    y = np.empty(n)
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return True


@njit(cache=True, error_model="numpy")
def refine_pose(
    Rq: np.ndarray, tq: np.ndarray, xq: np.ndarray, xr: np.ndarray, pair: np.ndarray, idx2d: np.ndarray,
    f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray,
    xq3d: np.ndarray, X3d: np.ndarray, idx3d: np.ndarray, loss_scale: float, max_iterations: int,
    sigma_floor: float, c0: np.ndarray, B: np.ndarray, fixed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Refine ``query_from_world`` on the given inliers.

    Args:
        Rq: (3, 3) initial rotation of ``query_from_world``; tq is ignored in favour of
            the centre ``c0`` (kept in the signature for symmetry with the loop).
        c0, B: the centre is parametrised as ``c = c0 + B p`` with B (3, 3) orthonormal.
        fixed: (6,) bool; parameters held at their initial value (rotation 0-2, centre 3-5),
            used to profile the cost along one direction (degeneracy test).
        idx2d: (K,) rows of inlier 2D-2D matches; idx3d: (L,) rows of inlier 2D-3D constraints.
        loss_scale: Cauchy scale σ in pixels.
        sigma_floor: lower bound on σ̂ in pixels for the covariance, so that noise-free or
            overfitted residuals cannot make an ill-conditioned position look certain.

    Returns:
        R (3, 3), t (3,), the (6, 6) normal matrix ``JᵀWJ`` at the solution (parameters
        ``(δ, p)``; see :func:`centre_covariance`), the residual scale σ̂ in pixels, and the
        final robust cost.
    """
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    R = Rq.copy()
    c = c0.copy()
    zero = np.zeros(6)
    r = np.empty(m)
    rp = np.empty(m)
    J = np.empty((m, 6))
    H = np.empty((6, 6))
    g = np.empty(6)
    s2 = loss_scale * loss_scale
    lam = 1e-4
    _residuals_jacobian(R, c, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, r, J)
    cost = 0.5 * s2 * np.sum(np.log1p(r * r / s2))
    wr2 = 0.0
    for it in range(max_iterations + 1):
        for k in range(6):
            if fixed[k]:
                J[:, k] = 0.0
        H[:] = 0.0
        g[:] = 0.0
        wr2 = 0.0
        for i in range(m):
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
        if it == max_iterations:
            break
        improved = False
        step = np.zeros(6)
        for _try in range(6):
            A = H.copy()
            for k in range(6):
                A[k, k] += lam * max(H[k, k], 1e-12)
                if fixed[k]:
                    A[k, k] = 1.0
            if not _solve_spd(A, -g, step):
                lam *= 10.0
                continue
            R_new = m3.mul(_exp_so3(step[:3]), R)
            c_new = c + m3.vec(B, step[3:])
            _residuals(zero, R_new, c_new, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, rp)
            new_cost = 0.5 * s2 * np.sum(np.log1p(rp * rp / s2))
            if new_cost <= cost:
                R, c = R_new, c_new
                improved = cost - new_cost > 1e-6 * cost
                cost = new_cost
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        if improved or _try < 6:
            _residuals_jacobian(R, c, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, r, J)
        if not improved or np.sqrt(np.sum(step * step)) < 1e-9:
            max_iterations = it + 1  # one more pass to evaluate H at the solution
    # The normal matrix JᵀWJ at the solution; the covariance σ̂² (JᵀWJ)⁻¹ is formed by the caller.
    dof = max(m - 6, 1)
    sigma2 = max(wr2 / dof, sigma_floor * sigma_floor)
    t = -m3.vec(R, c)
    return R, t, H.copy(), np.sqrt(sigma2), cost


@njit(cache=True, error_model="numpy")
def refine_on_inliers(
    Rq: np.ndarray, tq: np.ndarray, xq: np.ndarray, xr: np.ndarray, pair: np.ndarray, offsets: np.ndarray,
    f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray,
    xq3d: np.ndarray, X3d: np.ndarray, inlier_threshold_sq: float, loss_scale: float, max_iterations: int,
    sigma_floor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, np.ndarray, np.ndarray]:
    """:func:`refine_pose` on the inliers of the initial pose, in one call.

    The inliers are the 2D-2D matches (Sampson) and 2D-3D constraints (reprojection) whose
    squared pixel error at ``(Rq, tq)`` is below ``inlier_threshold_sq``; with fewer than 6
    of them the pose is returned unchanged (cost inf).

    Returns:
        R, t, the normal matrix H, σ̂, cost (as :func:`refine_pose`), and the inlier masks
        (N,), (M,) bool at the initial pose.
    """
    e2d, e3d = errors_sq(Rq, tq, xq, xr, offsets, f_query, f_ref, ref_R, ref_t, xq3d, X3d)
    in2d = e2d < inlier_threshold_sq
    in3d = e3d < inlier_threshold_sq
    idx2d = np.flatnonzero(in2d)
    idx3d = np.flatnonzero(in3d)
    if idx2d.shape[0] + idx3d.shape[0] < 6:
        return Rq.copy(), tq.copy(), np.zeros((6, 6)), np.inf, np.inf, in2d, in3d
    c0 = -m3.t_vec(Rq, tq)
    R, t, H, sigma, cost = refine_pose(Rq, tq, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d,
                                       idx3d, loss_scale, max_iterations, sigma_floor, c0, np.eye(3),
                                       np.zeros(6, dtype=np.bool_))
    return R, t, H, sigma, cost, in2d, in3d


@njit(cache=True, error_model="numpy")
def map_uncertainty_covariance(
    Rq: np.ndarray, tq: np.ndarray, xq: np.ndarray, xr: np.ndarray, pair: np.ndarray, idx2d: np.ndarray,
    f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray,
    xq3d: np.ndarray, X3d: np.ndarray, idx3d: np.ndarray, loss_scale: float,
    rotation_std_rad: float, position_std_m: float,
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
        parameters; :func:`map_covariance_from_parts` forms the centre covariance (numpy
        linear algebra stays outside numba, whose LAPACK bindings are slow to compile).
    """
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    R0 = Rq.copy()
    c0 = -(Rq.T @ tq)
    B = np.eye(3)
    zero = np.zeros(6)
    r = np.empty(m)
    rp = np.empty(m)
    _residuals(zero, R0, c0, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, r)
    s2 = loss_scale * loss_scale
    w = 1.0 / (1.0 + r * r / s2)
    J = np.empty((m, 6))
    for k in range(6):
        h = 1e-7 if k < 3 else 1e-7 * max(1.0, np.abs(c0).max())
        pp = zero.copy()
        pp[k] += h
        _residuals(pp, R0, c0, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, rp)
        J[:, k] = (rp - r) / h
    P = ref_R.shape[0]
    Jr = np.zeros((m, 6 * P))
    no3d = np.zeros(0, dtype=np.int64)
    for p in range(P):
        # A reference pose only moves the residuals of its own pair (3D points are held fixed).
        rows = np.flatnonzero(pair[idx2d] == p)
        if rows.shape[0] == 0:
            continue
        sub = idx2d[rows]
        base = np.empty(rows.shape[0])
        pert = np.empty(rows.shape[0])
        _residuals(zero, R0, c0, B, xq, xr, pair, sub, f_query, f_ref, ref_R, ref_t, xq3d, X3d, no3d, base)
        c_ref = -(ref_R[p].T @ ref_t[p])
        Rp = ref_R.copy()
        tp = ref_t.copy()
        for k in range(6):
            h = 1e-7 if k < 3 else 1e-7 * max(1.0, np.abs(c_ref).max())
            if k < 3:
                dw = np.zeros(3)
                dw[k] = h
                Rp[p] = _exp_so3(dw) @ ref_R[p]
                tp[p] = -(Rp[p] @ c_ref)
            else:
                dc = c_ref.copy()
                dc[k - 3] += h
                Rp[p] = ref_R[p]
                tp[p] = -(ref_R[p] @ dc)
            _residuals(zero, R0, c0, B, xq, xr, pair, sub, f_query, f_ref, Rp, tp, xq3d, X3d, no3d, pert)
            for n in range(rows.shape[0]):
                Jr[rows[n], 6 * p + k] = (pert[n] - base[n]) / h
    JW = J * w[:, None]
    var = np.empty(6 * P)
    for p in range(P):
        for k in range(6):
            var[6 * p + k] = rotation_std_rad**2 if k < 3 else position_std_m**2
    return JW.T @ J, JW.T @ Jr, var


def centre_covariance(H: np.ndarray, sigma: float, B: np.ndarray = np.eye(3)) -> np.ndarray:
    """(3, 3) covariance of the camera centre ``σ̂² B (H⁻¹)[3:, 3:] Bᵀ`` from the normal matrix.

    Inf-filled when H is singular relative to its scale (an unobservable direction).
    """
    ev, V = np.linalg.eigh(H)
    if not (ev[0] > 1e-12 * ev[-1] and ev[0] > 0):
        return np.full((3, 3), np.inf)
    Vc = V[3:]  # (H⁻¹)[3:, 3:] = V[3:] diag(1/ev) V[3:]ᵀ
    cov = (Vc / ev) @ Vc.T
    return sigma * sigma * (B @ cov @ B.T)


def map_covariance_from_parts(H: np.ndarray, M: np.ndarray, var: np.ndarray) -> np.ndarray:
    """``B diag(var) Bᵀ`` with ``B = H⁻¹ M``, centre block; inf-filled when H is singular."""
    ev = np.linalg.eigvalsh(H)
    if not (ev[0] > 1e-12 * ev[-1] and ev[0] > 0):
        return np.full((3, 3), np.inf)
    Bm = np.linalg.solve(H, M)
    return ((Bm * var[None, :]) @ Bm.T)[3:, 3:]
