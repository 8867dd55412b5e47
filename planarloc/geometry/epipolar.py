"""Two-view epipolar geometry shared by solvers, estimators and refinement.

All functions take normalized homogeneous coordinates ``x = (x/z, y/z, 1)`` (or any bearing
vector with positive z-direction) with the constraint ``x_refᵀ E x_query = 0`` for
``E = [t]x R`` and ``ref_from_query = (R, t)``. Arrays are N-first; leading batch dimensions
broadcast.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices with ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def essential_from_relpose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``E = [t]x R`` for ``x_b = R x_a + t``; (..., 3, 3), (..., 3) -> (..., 3, 3)."""
    return skew(t) @ R


def sampson_error_sq(
    E: np.ndarray,
    x_query: np.ndarray,
    x_ref: np.ndarray,
    f_query: tuple[float, float] | np.ndarray = (1.0, 1.0),
    f_ref: tuple[float, float] | np.ndarray = (1.0, 1.0),
) -> np.ndarray:
    """Squared Sampson error of ``x_refᵀ E x_query = 0``, optionally in pixels.

    Args:
        E: (3, 3) essential matrix, ``x_refᵀ E x_query = 0``.
        x_query, x_ref: (N, 3) normalized homogeneous points (third coordinate 1).
        f_query, f_ref: (fx, fy) focal lengths of the two cameras. With the defaults the error
            is in normalized units; with the true focal lengths it is the Sampson error of the
            fundamental matrix ``K_ref⁻ᵀ E K_query⁻¹`` in pixels (Hartley & Zisserman eq. 11.9).

    Returns:
        (N,) squared errors.
    """
    Ex = x_query @ E.T  # (N, 3): E x_query
    Etx = x_ref @ E  # (N, 3): Eᵀ x_ref
    r = np.einsum("ij,ij->i", x_ref, Ex)
    fq = np.asarray(f_query, dtype=float)
    fr = np.asarray(f_ref, dtype=float)
    den = (
        (Ex[:, 0] / fr[0]) ** 2
        + (Ex[:, 1] / fr[1]) ** 2
        + (Etx[:, 0] / fq[0]) ** 2
        + (Etx[:, 1] / fq[1]) ** 2
    )
    return r * r / np.maximum(den, 1e-300)


def triangulation_depths(R: np.ndarray, t: np.ndarray, x_query: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """Depths ``(λ_query, λ_ref)`` with ``λ_ref x_ref ≈ λ_query R x_query + t`` (midpoint method).

    Args:
        R, t: ``ref_from_query``.
        x_query, x_ref: (N, 3) rays.

    Returns:
        (N, 2) depths along the given rays; NaN where the rays are parallel (no baseline or
        a point at infinity), so that any ``> 0`` test on them fails.
    """
    a = x_query @ R.T  # query rays in the reference frame
    b = x_ref
    # Minimise |λq a + t - λr b|²: normal equations of a 2x2 system.
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b, b)
    ab = np.einsum("ij,ij->i", a, b)
    at = a @ t
    bt = b @ t
    det = aa * bb - ab * ab
    ok = det > 1e-12 * aa * bb
    with np.errstate(divide="ignore", invalid="ignore"):
        lq = (-at * bb + ab * bt) / det
        lr = (aa * bt - ab * at) / det
    out = np.stack([lq, lr], axis=1)
    out[~ok] = np.nan
    return out


def triangulate_points(
    cam_from_world_a: tuple[np.ndarray, np.ndarray],
    cam_from_world_b: tuple[np.ndarray, np.ndarray],
    x_a: np.ndarray,
    x_b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation of (N, 3) rays seen by two cameras with known poses.

    Args:
        cam_from_world_a, cam_from_world_b: (R (3, 3), t (3,)) of each camera.
        x_a, x_b: (N, 3) normalized homogeneous points in each camera.

    Returns:
        points (N, 3) in world coordinates (NaN where rays are parallel) and the
        triangulation angle (N,) in degrees.
    """
    Ra, ta = cam_from_world_a
    Rb, tb = cam_from_world_b
    R = Rb @ Ra.T
    t = tb - R @ ta
    depths = triangulation_depths(R, t, x_a, x_b)
    Xa = x_a * depths[:, :1]
    Xb_in_a = (x_b * depths[:, 1:2] - t) @ R  # R^T (λ x_b - t)
    X_a = 0.5 * (Xa + Xb_in_a)
    X_world = (X_a - ta) @ Ra
    da = x_a @ Ra  # ray directions in world
    db = x_b @ Rb
    cosang = np.einsum("ij,ij->i", da, db) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
    angle = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    bad = ~np.all(depths > 0, axis=1)
    X_world[bad] = np.nan
    return X_world, angle


def projection_jacobians(
    X: np.ndarray, R: np.ndarray, t: np.ndarray, focal: tuple[float, float] | np.ndarray
) -> np.ndarray:
    """(N, 2, 3) derivatives of the pixel projections of world points X (N, 3) w.r.t. X.

    For the pinhole camera ``cam_from_world = (R, t)`` with focal lengths ``(fx, fy)``:
    ``∂u/∂X = f/z [1, 0, −x/z] R`` and likewise for v (lens distortion not included).
    """
    Xc = X @ R.T + t
    fx, fy = float(focal[0]), float(focal[1])
    z = Xc[:, 2]
    J = np.zeros((len(X), 2, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        J[:, 0, 0] = fx / z
        J[:, 0, 2] = -fx * Xc[:, 0] / (z * z)
        J[:, 1, 1] = fy / z
        J[:, 1, 2] = -fy * Xc[:, 1] / (z * z)
    return J @ R


class TriangulationUncertainty(NamedTuple):
    """First-order uncertainty of points triangulated from two views (:func:`triangulation_uncertainty`).

    Attributes:
        cov: (N, 3, 3) covariance of each point from its keypoints' pixel noise.
        pose_jac: (N, 2, 3, 6) ``∂X/∂(ω, d)`` of each point for a correction of either view's pose.
    """

    cov: np.ndarray
    pose_jac: np.ndarray


def triangulation_uncertainty(
    X: np.ndarray,
    cam_from_world_a: tuple[np.ndarray, np.ndarray],
    cam_from_world_b: tuple[np.ndarray, np.ndarray],
    focal_a: tuple[float, float] | np.ndarray,
    focal_b: tuple[float, float] | np.ndarray,
    keypoint_std_px: float,
) -> TriangulationUncertainty:
    """How points X (N, 3) triangulated from two views move with the keypoint noise and with
    corrections of the views' poses; poses and focal lengths are one per view or one per point
    ((N, 3, 3), (N, 3), (N, 2)).

    **Pixel noise**: ``Σ = σ² (J_aᵀ J_a + J_bᵀ J_b)⁻¹`` with ``J`` the pixel projection Jacobians
    in the two views (:func:`projection_jacobians`) and σ = ``keypoint_std_px`` (Hartley &
    Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 5.2.3, backward propagation of covariance).
    A far point seen at a small angle has a covariance elongated along the viewing rays: its depth
    is uncertain.

    **Pose corrections**: a view's correction is ``(ω, d)``: ``R' = Exp(ω) R`` (ω in the camera
    frame, radians) and the centre moved by ``d`` (world frame, metres), the parametrisation of the
    map prior (:mod:`planarloc.robust.map_prior`). ``pose_jac[:, 0]`` is ``∂X/∂(ω_a, d_a)``,
    ``pose_jac[:, 1]`` ``∂X/∂(ω_b, d_b)``. The point is the least-squares triangulation of its two
    observations, ``min_X Σ_v |u_v(X) − ū_v|²``; by the implicit function theorem
    ``∂X/∂θ_v = −(Σ_w J_wᵀ J_w)⁻¹ J_vᵀ ∂u_v/∂θ_v``, ``∂u_v/∂ω = −P_v [X_v]x`` and
    ``∂u_v/∂d = −J_v`` (``P_v`` the pixel Jacobian at the camera-frame point ``X_v``). Moving both
    centres by ``d`` moves the point by ``d``. A pose error is shared by every point triangulated
    from that view, so unlike the pixel noise it does not average out over points.

    Both come from the same information matrix, in one compiled pass. NaN rows for points on the
    baseline (singular information).

    References:
        Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 5.2 (propagation of
        covariance through an implicit function).
    """
    X = np.ascontiguousarray(X, dtype=float)
    n = len(X)

    def per_point(a: object, shape: tuple[int, ...]) -> np.ndarray:
        return np.broadcast_to(np.asarray(a, dtype=float), (n, *shape)).copy()  # writable, C order

    cov, jac = np.empty((n, 3, 3)), np.empty((n, 2, 3, 6))
    _uncertainty_kernel(
        X,
        per_point(cam_from_world_a[0], (3, 3)),
        per_point(cam_from_world_a[1], (3,)),
        per_point(focal_a, (2,)),
        per_point(cam_from_world_b[0], (3, 3)),
        per_point(cam_from_world_b[1], (3,)),
        per_point(focal_b, (2,)),
        float(keypoint_std_px) ** 2,
        cov,
        jac,
    )
    return TriangulationUncertainty(cov, jac)


@njit(cache=True, error_model="numpy")
def _uncertainty_kernel(
    X: np.ndarray,
    Ra: np.ndarray,
    ta: np.ndarray,
    fa: np.ndarray,
    Rb: np.ndarray,
    tb: np.ndarray,
    fb: np.ndarray,
    var_px: float,
    cov: np.ndarray,
    out: np.ndarray,
) -> None:
    """:func:`triangulation_uncertainty` into ``cov`` (N, 3, 3) and ``out`` (N, 2, 3, 6) for
    per-point poses (N, 3, 3), (N, 3), focal lengths (N, 2) and the pixel variance ``var_px``: one
    compiled pass (numpy spent ~120 µs on the small arrays of one query's points)."""
    G = np.empty((2, 3, 3))  # J_vᵀ J_v
    K = np.empty((2, 3, 3))  # J_vᵀ P_v [X_v]x = −J_vᵀ ∂u_v/∂ω
    PtP = np.zeros((3, 3))
    S = np.zeros((3, 3))
    for i in range(X.shape[0]):
        for v in range(2):
            R, t, f = (Ra[i], ta[i], fa[i]) if v == 0 else (Rb[i], tb[i], fb[i])
            Xc = m3.vec(R, X[i]) + t
            iz = 1.0 / Xc[2]
            x, y = Xc[0] * iz, Xc[1] * iz
            # PᵀP of the pixel Jacobian P = diag(f) / z [[1, 0, −x], [0, 1, −y]] (camera frame)
            fx2, fy2 = (f[0] * iz) ** 2, (f[1] * iz) ** 2
            PtP[0, 0], PtP[1, 1], PtP[2, 2] = fx2, fy2, fx2 * x * x + fy2 * y * y
            PtP[0, 2] = PtP[2, 0] = -fx2 * x
            PtP[1, 2] = PtP[2, 1] = -fy2 * y
            S[0, 1], S[0, 2], S[1, 0], S[1, 2], S[2, 0], S[2, 1] = -Xc[2], Xc[1], Xc[2], -Xc[0], -Xc[1], Xc[0]
            RtG = m3.t_mul(R, PtP)
            m3.store_mat(G, v, m3.mul(RtG, R))
            m3.store_mat(K, v, m3.mul(RtG, S))
        A = G[0] + G[1]
        c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
        c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
        c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
        det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
        trace = A[0, 0] + A[1, 1] + A[2, 2]
        if not (np.isfinite(det) and det > 1e-12 * trace**3):  # a point on the baseline
            cov[i] = np.nan
            out[i] = np.nan
            continue
        Ai = np.empty((3, 3))
        Ai[0, 0], Ai[1, 0], Ai[2, 0] = c00 / det, c01 / det, c02 / det
        Ai[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) / det
        Ai[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) / det
        Ai[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) / det
        Ai[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) / det
        Ai[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) / det
        Ai[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) / det
        for a in range(3):
            for b in range(3):
                cov[i, a, b] = 0.5 * var_px * (Ai[a, b] + Ai[b, a])  # exactly symmetric
        # ∂X/∂θ_v = −A⁻¹ J_vᵀ ∂u_v/∂θ_v = A⁻¹ [J_vᵀ P_v [X_v]x, J_vᵀ J_v]
        for v in range(2):
            AK, AG = m3.mul(Ai, K[v]), m3.mul(Ai, G[v])
            for a in range(3):
                for b in range(3):
                    out[i, v, a, b] = AK[a, b]
                    out[i, v, a, 3 + b] = AG[a, b]
