"""Scalar epipolar and reprojection kernels for numba code: one definition of each error.

Every compiled error in planarloc goes through these (scoring, local optimisation and final
refinement, hypothesis checks, relative-pose RANSAC), so inlier decisions, MSAC costs and the
residuals the refinement minimises are the same numbers. They are ``inline="always"``: called
per match in the hot loops, a function call would cost more than the arithmetic.
:mod:`planarloc.geometry.epipolar` has the vectorised numpy versions for Python callers.

Conventions: ``x_refᵀ E x_query = 0`` with ``E = [t]x R`` for ``ref_from_query = (R, t)``;
rays are normalized homogeneous points ``(x, y, 1)``; focal lengths scale errors to pixels.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3

# Below this Sampson denominator a match has no defined error (E x and Eᵀ x vanish).
DEN_FLOOR = 1e-300
NO_ERROR_SQ = 1e300  # squared error reported for such a match or a point behind the camera


@njit(cache=True, inline="always", error_model="numpy")
def _cross_times_into(t0: float, t1: float, t2: float, R: np.ndarray, E: np.ndarray) -> None:
    for j in range(3):
        E[0, j] = -t2 * R[1, j] + t1 * R[2, j]
        E[1, j] = t2 * R[0, j] - t0 * R[2, j]
        E[2, j] = -t1 * R[0, j] + t0 * R[1, j]


@njit(cache=True, inline="always", error_model="numpy")
def essential_into(R: np.ndarray, t: np.ndarray, E: np.ndarray) -> None:
    """Write ``E = [t]x R`` (3, 3) of ``b_from_a = (R, t)`` into E."""
    _cross_times_into(t[0], t[1], t[2], R, E)


@njit(cache=True, inline="always", error_model="numpy")
def relative_essential_into(
    Rp: np.ndarray, tp: np.ndarray, Rq: np.ndarray, tq: np.ndarray, E: np.ndarray
) -> None:
    """E of ``p_from_query = (R_p R_qᵀ, t_p − R_p R_qᵀ t_q)`` for two ``cam_from_world`` poses."""
    R = m3.mul_t(Rp, Rq)
    t0 = tp[0] - (R[0, 0] * tq[0] + R[0, 1] * tq[1] + R[0, 2] * tq[2])
    t1 = tp[1] - (R[1, 0] * tq[0] + R[1, 1] * tq[1] + R[1, 2] * tq[2])
    t2 = tp[2] - (R[2, 0] * tq[0] + R[2, 1] * tq[1] + R[2, 2] * tq[2])
    _cross_times_into(t0, t1, t2, R, E)


@njit(cache=True, inline="always", error_model="numpy")
def sampson_terms(
    E: np.ndarray, q: np.ndarray, r: np.ndarray, fq0: float, fq1: float, fr0: float, fr1: float
) -> tuple[float, float]:
    """Algebraic residual ``rᵀ E q`` and the Sampson denominator in pixels
    ``(Eq)₀²/fr0² + (Eq)₁²/fr1² + (Eᵀr)₀²/fq0² + (Eᵀr)₁²/fq1²`` (Hartley & Zisserman eq. 11.9)."""
    Ex0 = E[0, 0] * q[0] + E[0, 1] * q[1] + E[0, 2] * q[2]
    Ex1 = E[1, 0] * q[0] + E[1, 1] * q[1] + E[1, 2] * q[2]
    Ex2 = E[2, 0] * q[0] + E[2, 1] * q[1] + E[2, 2] * q[2]
    Etx0 = E[0, 0] * r[0] + E[1, 0] * r[1] + E[2, 0] * r[2]
    Etx1 = E[0, 1] * r[0] + E[1, 1] * r[1] + E[2, 1] * r[2]
    res = r[0] * Ex0 + r[1] * Ex1 + r[2] * Ex2
    return res, (Ex0 / fr0) ** 2 + (Ex1 / fr1) ** 2 + (Etx0 / fq0) ** 2 + (Etx1 / fq1) ** 2


@njit(cache=True, inline="always", error_model="numpy")
def sampson_sq(
    E: np.ndarray, q: np.ndarray, r: np.ndarray, fq0: float, fq1: float, fr0: float, fr1: float
) -> float:
    """Squared Sampson error in pixels; ``NO_ERROR_SQ`` where it is undefined."""
    res, den = sampson_terms(E, q, r, fq0, fq1, fr0, fr1)
    if den < DEN_FLOOR:
        return NO_ERROR_SQ
    return res * res / den


@njit(cache=True, inline="always", error_model="numpy")
def sampson_signed(
    E: np.ndarray, q: np.ndarray, r: np.ndarray, fq0: float, fq1: float, fr0: float, fr1: float
) -> float:
    """Signed Sampson error in pixels (the refinement's residual; its square is :func:`sampson_sq`)."""
    res, den = sampson_terms(E, q, r, fq0, fq1, fr0, fr1)
    return res / np.sqrt(max(den, DEN_FLOOR))


@njit(cache=True, inline="always", error_model="numpy")
def project(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[float, float, float]:
    """Normalized image coordinates ``(u, v)`` and depth z of world point X (3,) in the camera
    ``cam_from_world = (R, t)``; the division uses ``max(z, 1e-6)`` (z ≤ 0: behind the camera)."""
    z = R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2] + t[2]
    zc = max(z, 1e-6)
    u = (R[0, 0] * X[0] + R[0, 1] * X[1] + R[0, 2] * X[2] + t[0]) / zc
    v = (R[1, 0] * X[0] + R[1, 1] * X[1] + R[1, 2] * X[2] + t[1]) / zc
    return u, v, z


@njit(cache=True, inline="always", error_model="numpy")
def reprojection_sq(
    R: np.ndarray, t: np.ndarray, X: np.ndarray, x: np.ndarray, fq0: float, fq1: float
) -> float:
    """Squared reprojection error in pixels of X observed at ray x (3,); ``NO_ERROR_SQ`` for a
    point not in front of the camera (depth ≤ 1e-9)."""
    u, v, z = project(R, t, X)
    if z <= 1e-9:
        return NO_ERROR_SQ
    du = (u - x[0] / x[2]) * fq0
    dv = (v - x[1] / x[2]) * fq1
    return du * du + dv * dv
