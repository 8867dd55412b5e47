"""Robust 6DoF refinement of the query pose over all inliers (paper Sec. IV-B, last paragraph).

Minimises ``Σ ρ(r)`` with the Cauchy loss ``ρ(r) = σ²/2 · log(1 + r²/σ²)`` over the signed
Sampson errors (pixels) of the inlier 2D-2D matches and the reprojection errors (pixels,
2 per constraint) of the inlier 2D-3D constraints, by Levenberg-Marquardt with IRLS
weights. Parameters: a rotation increment ``δ`` (``R = Exp(δ) R₀``) and the camera
centre ``c`` directly, so that the position covariance is a block of the inverse normal
matrix: ``Σ_c = σ̂² (JᵀWJ)⁻¹[3:, 3:]``. Its largest eigenvalue gives ``position_std_m``;
with 2D-2D constraints only and the query collinear with the reference centres it blows up
(the scale along the line is unobservable), which is how degeneracy is detected.

The Jacobian is by forward differences (6 parameters, a dozen residual evaluations of
~1k residuals per iteration); an analytic Sampson Jacobian would be longer and no faster.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.robust.scoring import _relative_essential


@njit(cache=True, error_model="numpy")
def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / (th * th) * (K @ K)


@njit(cache=True, error_model="numpy")
def _residuals(
    params: np.ndarray, R0: np.ndarray, c0: np.ndarray, B: np.ndarray, xq: np.ndarray, xr: np.ndarray,
    pair: np.ndarray, idx2d: np.ndarray, f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray,
    ref_t: np.ndarray, xq3d: np.ndarray, X3d: np.ndarray, idx3d: np.ndarray, out: np.ndarray,
) -> None:
    Rq = _exp_so3(params[:3]) @ R0
    c = c0 + B @ params[3:]
    tq = -(Rq @ c)
    P = ref_R.shape[0]
    Es = np.empty((P, 3, 3))  # P small: one allocation per evaluation
    for p in range(P):
        _relative_essential(ref_R[p], ref_t[p], Rq, tq, Es[p])
    fq0, fq1 = f_query[0], f_query[1]
    for n in range(idx2d.shape[0]):
        i = idx2d[n]
        p = pair[i]
        E = Es[p]
        q, r = xq[i], xr[i]
        Ex0 = E[0, 0] * q[0] + E[0, 1] * q[1] + E[0, 2] * q[2]
        Ex1 = E[1, 0] * q[0] + E[1, 1] * q[1] + E[1, 2] * q[2]
        Ex2 = E[2, 0] * q[0] + E[2, 1] * q[1] + E[2, 2] * q[2]
        Etx0 = E[0, 0] * r[0] + E[1, 0] * r[1] + E[2, 0] * r[2]
        Etx1 = E[0, 1] * r[0] + E[1, 1] * r[1] + E[2, 1] * r[2]
        res = r[0] * Ex0 + r[1] * Ex1 + r[2] * Ex2
        den = (Ex0 / f_ref[p, 0]) ** 2 + (Ex1 / f_ref[p, 1]) ** 2 + (Etx0 / fq0) ** 2 + (Etx1 / fq1) ** 2
        out[n] = res / np.sqrt(max(den, 1e-300))
    m0 = idx2d.shape[0]
    for n in range(idx3d.shape[0]):
        i = idx3d[n]
        X = X3d[i]
        Xc = Rq @ X + tq
        z = max(Xc[2], 1e-6)
        out[m0 + 2 * n] = (Xc[0] / z - xq3d[i, 0] / xq3d[i, 2]) * fq0
        out[m0 + 2 * n + 1] = (Xc[1] / z - xq3d[i, 1] / xq3d[i, 2]) * fq1


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
        R (3, 3), t (3,), the (3, 3) covariance of the camera centre in world units²
        (inf-filled when singular), the residual scale σ̂ in pixels, and the final robust cost.
    """
    m = idx2d.shape[0] + 2 * idx3d.shape[0]
    params = np.zeros(6)
    R0 = Rq.copy()
    r = np.empty(m)
    rp = np.empty(m)
    J = np.empty((m, 6))
    H = np.empty((6, 6))
    g = np.empty(6)
    s2 = loss_scale * loss_scale
    lam = 1e-4
    _residuals(params, R0, c0, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, r)
    cost = 0.5 * s2 * np.sum(np.log1p(r * r / s2))
    for it in range(max_iterations + 1):
        # Forward-difference Jacobian and IRLS-weighted normal equations.
        for k in range(6):
            if fixed[k]:
                J[:, k] = 0.0
                continue
            h = 1e-7 if k < 3 else 1e-7 * max(1.0, np.abs(c0).max())
            pp = params.copy()
            pp[k] += h
            _residuals(pp, R0, c0, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, rp)
            for i in range(m):
                J[i, k] = (rp[i] - r[i]) / h
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
            if np.linalg.det(A) == 0.0:
                lam *= 10.0
                continue
            step = -np.linalg.solve(A, g)
            pp = params + step
            _residuals(pp, R0, c0, B, xq, xr, pair, idx2d, f_query, f_ref, ref_R, ref_t, xq3d, X3d, idx3d, rp)
            new_cost = 0.5 * s2 * np.sum(np.log1p(rp * rp / s2))
            if new_cost <= cost:
                params = pp
                r[:] = rp
                improved = cost - new_cost > 1e-8 * cost
                cost = new_cost
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        if not improved or np.sqrt(np.sum(step * step)) < 1e-9:
            max_iterations = it + 1  # one more pass to evaluate H at the solution
    # Covariance of the centre at the solution: σ̂² (JᵀWJ)⁻¹, scale-aware singularity test.
    dof = max(m - 6, 1)
    sigma2 = max(wr2 / dof, sigma_floor * sigma_floor)
    cov_c = np.full((3, 3), np.inf)
    if not fixed.any():
        ev = np.linalg.eigvalsh(H)
        if ev[0] > 1e-12 * ev[-1] and ev[0] > 0:
            Hinv = np.linalg.inv(H)
            cov_c = sigma2 * (B @ Hinv[3:, 3:] @ B.T)
    R = _exp_so3(params[:3]) @ R0
    t = -(R @ (c0 + B @ params[3:]))
    return R, t, cov_c, np.sqrt(sigma2), cost
