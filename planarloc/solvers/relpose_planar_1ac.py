"""Planar relative pose from one affine correspondence (Guan et al., CVPR 2020, Sec. 3.1).

An affine correspondence is a point match ``(x_q, x_r)`` with the local affine map
``A = ∂x_r / ∂x_q`` (2x2, in normalized image coordinates) that takes a small patch around
``x_q`` in the query image to the matching patch in the reference image.

Derivation (ours, matching the paper's). With ``x_q = (u1, v1, 1)``, ``x_r = (u2, v2, 1)`` and
the planar essential matrix of our paper's eq. (2)::

    E = [[0, e01, 0], [e10, 0, e12], [0, e21, 0]]
      = ρ [[0, cos(θ-φ), 0], [-cos φ, 0, sin φ], [0, sin(θ-φ), 0]]

the epipolar constraint ``x_rᵀ E x_q = 0`` (eq. 3) holds for every point of the patch,
``x_r(x_q)ᵀ E x_q ≡ 0``. Differentiating with respect to ``(u1, v1)`` gives the affine–essential
relation (Guan et al. eq. 4, after Barath & Hajder 2018)::

    (Eᵀ x_r)_{1:2} + Aᵀ (E x_q)_{1:2} = 0.

(The form ``Aᵀ (Eᵀ x_r)_{1:2} + (E x_q)_{1:2} = 0`` is the same relation for the inverse map
``A⁻¹ = ∂x_q / ∂x_r``.) With ``E x_q = (e01 v1, e10 u1 + e12, e21 v1)`` and
``Eᵀ x_r = (e10 v2, e01 u2 + e21, e12 v2)`` the three constraints are linear in the paper's
``x = (sin(θ-φ), cos(θ-φ), sin φ, cos φ)`` (our eq. 7; Guan et al. eq. 10)::

    [ v1   v1 u2            v2    -u1 v2         ]       (epipolar, eq. 5)
    [ 0    a00 v1           a10   -(a10 u1 + v2)  ] x = 0 (affine, column u1)
    [ 1    a01 v1 + u2      a11   -a11 u1         ]       (affine, column v1)

Three equations in a 2-DoF unknown: one affine correspondence over-determines planar motion.
Like the authors' closed-form solver (``1AC_CS``), we start from the one-dimensional null space
``n`` of this 3x4 matrix (rows normalised). We compute it as the generalised cross product of
the three rows — their signed 3x3 minors — exact in one pass instead of an eigen-decomposition
of ``MᵀM``. On exact data ``n`` lies on the planar-essential cone ``x1² + x2² = x3² + x4²``
(the two circles of eq. 10 have the same radius ρ). ``1AC_CS`` then puts each pair
``(x1, x2)``, ``(x3, x4)`` on its unit circle separately, which ignores that constraint. We
instead move to the cone point nearest to ``n`` in the plane ``span{n, v}``, ``v`` the next
right singular vector of ``M`` (the direction ``M`` constrains least): the root of smallest
``|l|`` of the quadratic ``(n + l v)ᵀ diag(1, 1, -1, -1) (n + l v) = 0``. This is exact on
noise-free data (``l = 0``) and, under noise, cuts the median translation-direction error two-
to threefold (``benchmarks/solvers_1ac.py``: 1 px point noise 7.8° -> 2.6°, 2 % affine scale noise
20.7° -> 8.9°; the 90th percentile stays about the same). ``v`` comes from the closed-form
least eigenvector of the 3x3 ``M Mᵀ``, so the kernel costs about as much as the 2-point one. If
the plane does not meet the cone we keep ``1AC_CS``'s answer. ``θ`` and
``φ`` follow from eq. (11). The sign of ``x`` (``φ`` vs ``φ + π``, left open by the authors'
code) is fixed by the cheirality of the point. We report how far ``n`` is from the cone::

    imbalance = (x1² + x2² - x3² - x4²) / ‖x‖²  ∈ [-1, 1]

It is 0 on exact data and grows with the inconsistency of the affine frame (an affine map that
no planar motion produces); callers may reject samples above a threshold (``max_imbalance``).

Degenerate input returns no solution: zero baseline and a point at infinity (the rays and
their affine map follow the rotation alone, so the system has rank 2 and every φ fits), a point
on the horizon line of both views (``v1 = v2 = 0``, rank ≤ 2), rays with no finite normalized
coordinates (z ≤ 0), and a point that lies behind a camera for both signs of ``t``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array, plain_float64_pair
from planarloc.solvers.relpose_planar_2p import (
    check_rays_or_points,
    planar_depth_sign,
    planar_pose_into,
    planar_poses,
)

_EPS_RANK = 1e-10  # minimum 3-volume of the three unit rows (rank 3 test)
_EPS_PAIR = 1e-12  # minimum squared norm of a circle pair (x1, x2) or (x3, x4)


@njit(cache=True, inline="always", error_model="numpy")
def _least_eigvec_sym3(
    a00: float, a01: float, a02: float, a11: float, a12: float, a22: float
) -> tuple[bool, float, float, float]:
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix, in closed form
    (trigonometric eigenvalues, O. K. Smith, CACM 4(4), 1961; the vector as the largest cross
    product of two rows of ``A - λ I``). False when it is not unique (a repeated smallest
    eigenvalue) or not finite."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
    if not p > 1e-12 * max(abs(q), 1e-300):
        return False, 0.0, 0.0, 0.0
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = det / (2.0 * p * p * p)
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    c00, c11, c22 = a00 - lam, a11 - lam, a22 - lam
    # cross products of the rows (c00, a01, a02), (a01, c11, a12), (a02, a12, c22)
    x0, x1, x2 = a01 * a12 - a02 * c11, a02 * a01 - c00 * a12, c00 * c11 - a01 * a01
    y0, y1, y2 = a01 * c22 - a02 * a12, a02 * a02 - c00 * c22, c00 * a12 - a01 * a02
    z0, z1, z2 = c11 * c22 - a12 * a12, a12 * a02 - a01 * c22, a01 * a12 - c11 * a02
    nx = x0 * x0 + x1 * x1 + x2 * x2
    ny = y0 * y0 + y1 * y1 + y2 * y2
    nz = z0 * z0 + z1 * z1 + z2 * z2
    if nx >= ny and nx >= nz:
        v0, v1, v2, nv = x0, x1, x2, nx
    elif ny >= nz:
        v0, v1, v2, nv = y0, y1, y2, ny
    else:
        v0, v1, v2, nv = z0, z1, z2, nz
    if not nv > 1e-24 * p * p * p * p:
        return False, 0.0, 0.0, 0.0
    nv = np.sqrt(nv)
    return True, v0 / nv, v1 / nv, v2 / nv


_ZERO4 = (0.0, 0.0, 0.0, 0.0)


@njit(cache=True, error_model="numpy", inline="always")
def _ac_system(xq: np.ndarray, A: np.ndarray, xr: np.ndarray):
    """``(ok, m0, m1, m2)``: the rows of the 3x4 system M x = 0 (module docstring), normalised;
    not ok for an empty row (e.g. on the horizon of both views) or NaN."""
    u1, v1 = xq[0] / xq[2], xq[1] / xq[2]
    u2, v2 = xr[0] / xr[2], xr[1] / xr[2]
    a00, a01, a10, a11 = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
    m00, m01, m02, m03 = v1, v1 * u2, v2, -u1 * v2
    m10, m11, m12, m13 = 0.0, a00 * v1, a10, -(a10 * u1 + v2)
    m20, m21, m22, m23 = 1.0, a01 * v1 + u2, a11, -a11 * u1
    n0 = np.sqrt(m00 * m00 + m01 * m01 + m02 * m02 + m03 * m03)
    n1 = np.sqrt(m10 * m10 + m11 * m11 + m12 * m12 + m13 * m13)
    n2 = np.sqrt(m20 * m20 + m21 * m21 + m22 * m22 + m23 * m23)
    if not (n0 > 1e-300 and n1 > 1e-300 and n2 > 1e-300):
        return False, _ZERO4, _ZERO4, _ZERO4
    return (
        True,
        (m00 / n0, m01 / n0, m02 / n0, m03 / n0),
        (m10 / n1, m11 / n1, m12 / n1, m13 / n1),
        (m20 / n2, m21 / n2, m22 / n2, m23 / n2),
    )


@njit(cache=True, error_model="numpy", inline="always")
def _null_vector(m0, m1, m2):
    """Null vector of the 3x4 matrix with rows m0, m1, m2: generalised cross product,
    x_k = (-1)^k det(M without column k)."""
    m00, m01, m02, m03 = m0
    m10, m11, m12, m13 = m1
    m20, m21, m22, m23 = m2
    x1 = m01 * (m12 * m23 - m13 * m22) - m02 * (m11 * m23 - m13 * m21) + m03 * (m11 * m22 - m12 * m21)
    x2 = -(m00 * (m12 * m23 - m13 * m22) - m02 * (m10 * m23 - m13 * m20) + m03 * (m10 * m22 - m12 * m20))
    x3 = m00 * (m11 * m23 - m13 * m21) - m01 * (m10 * m23 - m13 * m20) + m03 * (m10 * m21 - m11 * m20)
    x4 = -(m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20))
    return x1, x2, x3, x4


@njit(cache=True, error_model="numpy", inline="always")
def _dot4(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@njit(cache=True, error_model="numpy", inline="always")
def _project_on_cone(m0, m1, m2, x, c1: float, c2: float):
    """``(ok, x, c1, c2)``: the null vector x moved onto the cone x1² + x2² = x3² + x4²
    (deviation from 1AC_CS, see the module docstring), with its circle-pair norms c1, c2.

    The cone point of span{x, y} nearest to x, y the next right singular vector of M (y = Mᵀ w,
    w the least eigenvector of M Mᵀ; y ⟂ x because M x = 0). Exact data: x is on the cone. Not
    ok if a circle pair vanishes after the move; without a real intersection x is returned
    unchanged (each pair is then put on its circle, the authors' 1AC_CS).
    """
    ok, w0, w1, w2 = _least_eigvec_sym3(
        _dot4(m0, m0), _dot4(m0, m1), _dot4(m0, m2), _dot4(m1, m1), _dot4(m1, m2), _dot4(m2, m2)
    )
    if not ok:
        return True, x, c1, c2
    y1 = w0 * m0[0] + w1 * m1[0] + w2 * m2[0]
    y2 = w0 * m0[1] + w1 * m1[1] + w2 * m2[1]
    y3 = w0 * m0[2] + w1 * m1[2] + w2 * m2[2]
    y4 = w0 * m0[3] + w1 * m1[3] + w2 * m2[3]
    ny = np.sqrt(y1 * y1 + y2 * y2 + y3 * y3 + y4 * y4)
    if not ny > 1e-300:
        return True, x, c1, c2
    nx = np.sqrt(c1 + c2)
    x1, x2, x3, x4 = x[0] / nx, x[1] / nx, x[2] / nx, x[3] / nx
    y1, y2, y3, y4 = y1 / ny, y2 / ny, y3 / ny, y4 / ny
    c1, c2 = c1 / (nx * nx), c2 / (nx * nx)
    # (x + l y) on the cone: p + 2 q l + r l² = 0 with the form diag(1, 1, -1, -1).
    p = x1 * x1 + x2 * x2 - x3 * x3 - x4 * x4
    q = x1 * y1 + x2 * y2 - x3 * y3 - x4 * y4
    r = y1 * y1 + y2 * y2 - y3 * y3 - y4 * y4
    disc = q * q - p * r
    if disc >= 0.0:
        # root of smallest |l|, in the cancellation-free form l = -p / (q ± sqrt(disc))
        den = q + np.sqrt(disc) if q >= 0.0 else q - np.sqrt(disc)
        if abs(den) > 1e-300:
            lam = -p / den
            x1, x2, x3, x4 = x1 + lam * y1, x2 + lam * y2, x3 + lam * y3, x4 + lam * y4
            c1 = x1 * x1 + x2 * x2
            c2 = x3 * x3 + x4 * x4
            if c1 < _EPS_PAIR or c2 < _EPS_PAIR:
                return False, (x1, x2, x3, x4), c1, c2
    return True, (x1, x2, x3, x4), c1, c2


@njit(cache=True, error_model="numpy")
def solve_planar_1ac(xq: np.ndarray, xr: np.ndarray, A: np.ndarray, out: np.ndarray) -> int:
    """Core solver on one affine correspondence; returns the number of solutions (0 or 1).

    Args:
        xq, xr: (3,) query / reference rays (``(x, y, 1)`` or bearings with z > 0).
        A: (2, 2) local affine map ``∂x_r/∂x_q`` in normalized image coordinates.
        out: (3,) output buffer: ``θ``, ``φ`` (eq. 1) and the cone imbalance (module docstring).

    Scalars and tuples only (the stages are inlined): the solve is ~150 floating-point
    operations and allocations would dominate.
    """
    if not (xq[2] > 0.0 and xr[2] > 0.0):
        return 0  # no finite normalized coordinates (or NaN)
    ok, m0, m1, m2 = _ac_system(xq, A, xr)
    if not ok:
        return 0
    x = _null_vector(m0, m1, m2)
    c1 = x[0] * x[0] + x[1] * x[1]
    c2 = x[2] * x[2] + x[3] * x[3]
    if not (c1 + c2 > _EPS_RANK * _EPS_RANK):
        return 0  # rank < 3: zero baseline, point at infinity, or a degenerate frame (or NaN)
    if c1 < _EPS_PAIR * (c1 + c2) or c2 < _EPS_PAIR * (c1 + c2):
        return 0  # one circle pair vanishes: the frame fits no planar motion
    imbalance = (c1 - c2) / (c1 + c2)
    ok, x, c1, c2 = _project_on_cone(m0, m1, m2, x, c1, c2)
    if not ok:
        return 0
    r1 = np.sqrt(c1)
    r2 = np.sqrt(c2)
    s1, co1 = x[0] / r1, x[1] / r1  # sin(θ-φ), cos(θ-φ)
    sp, cp = x[2] / r2, x[3] / r2  # sin φ, cos φ (up to the common sign of x)
    ct = co1 * cp - s1 * sp  # cos θ; invariant under x -> -x
    st = s1 * cp + co1 * sp
    sign = planar_depth_sign(ct, st, sp, cp, xq[0], xq[1], xq[2], xr[0], xr[1], xr[2])
    if sign == 2 or sign == 0:
        return 0  # a point at infinity, or behind a camera for both signs of t
    out[0] = np.arctan2(st, ct)
    out[1] = np.arctan2(sign * sp, sign * cp)
    out[2] = imbalance
    return 1


@njit(cache=True, error_model="numpy")
def _relposes(xq: np.ndarray, xr: np.ndarray, A: np.ndarray, max_imbalance: float, out: np.ndarray) -> int:
    """Validated single call: -1 unless the shapes are (3,), (3,), (2, 2) and finite, else the number
    of poses written as ``out[k, :3] = R``, ``out[k, 3] = t`` (eq. 1) into out (1, 4, 3)."""
    if xq.shape[0] != 3 or xr.shape[0] != 3 or A.shape[0] != 2 or A.shape[1] != 2:
        return -1
    for j in range(3):
        if not (np.isfinite(xq[j]) and np.isfinite(xr[j])):
            return -1
    for i in range(2):
        for j in range(2):
            if not np.isfinite(A[i, j]):
                return -1
    sol = np.empty(3)
    n = solve_planar_1ac(xq, xr, A, sol)
    if n == 1 and abs(sol[2]) > max_imbalance:
        return 0
    if n == 1:
        planar_pose_into(sol[0], sol[1], out[0, :3], out[0, 3])
    return n


@njit(cache=True, error_model="numpy")
def _solve_batch(xq: np.ndarray, xr: np.ndarray, A: np.ndarray, sol: np.ndarray, counts: np.ndarray) -> None:
    for i in range(xq.shape[0]):
        counts[i] = solve_planar_1ac(xq[i], xr[i], A[i], sol[i])


@njit(cache=True, error_model="numpy", parallel=True)
def _solve_batch_parallel(
    xq: np.ndarray, xr: np.ndarray, A: np.ndarray, sol: np.ndarray, counts: np.ndarray
) -> None:
    for i in prange(xq.shape[0]):
        counts[i] = solve_planar_1ac(xq[i], xr[i], A[i], sol[i])


_PARALLEL_MIN_BATCH = 4096  # below this, thread start-up costs more than it saves


def relpose_planar_1ac(
    x_query: object, x_ref: object, affine: object, max_imbalance: float = 1.0
) -> list[Pose]:
    """The planar relative pose ``ref_from_query`` of one affine correspondence.

    Args:
        x_query: (3,) normalized homogeneous point ``(x, y, 1)`` or bearing vector (z > 0) in the
            query camera (x right, y down = gravity, z forward); a (2,) point gets z = 1.
        x_ref: (3,) or (2,) matching point in the reference camera.
        affine: (2, 2) local affine map ``A = ∂x_ref/∂x_query`` in **normalized** image
            coordinates (``d(x_r, y_r) ≈ A d(x_q, y_q)``); from pixels use
            :func:`planarloc.features.affine_frames.normalized_affine`.
        max_imbalance: reject the solution when ``|imbalance| > max_imbalance`` (the
            inconsistency of the frame with planar motion, module docstring, in [0, 1]).
            The default 1.0 keeps every solution.

    Returns:
        At most one pose ``ref_from_query`` (``x_ref = R x_query + t``, ``R`` about y,
        ``‖t‖ = 1``, ``t_y = 0``) with the point in front of both cameras. Empty for degenerate
        input (zero baseline, a point at infinity, a point on the horizon of both views, a frame
        that fits no planar motion, a point behind a camera for both signs of ``t``).

    Raises:
        InputError: wrong shape or non-finite values.

    References:
        B. Guan, J. Zhao, Z. Li, F. Sun, F. Fraundorfer, "Minimal Solutions for Relative Pose
        with a Single Affine Correspondence", CVPR 2020, Sec. 3.1, eq. (4), (10) (closed-form
        ``1AC_CS`` solver); our paper's eq. (1), (2), (5), (11). Deviations: the null vector by
        signed minors instead of an eigen-decomposition, then projected onto the planar cone
        (module docstring; same result on exact data, ~3x smaller direction error under noise),
        the sign of ``t`` by cheirality, and the imbalance reported (``max_imbalance``).

    Example:
        >>> from planarloc.geometry.planar import relpose_from_planar_params
        >>> truth = relpose_from_planar_params(0.2, 0.5)
        >>> # x_q, x_r, A of a point on a surface patch (tests/solvers/test_relpose_planar_1ac.py)
        >>> # relpose_planar_1ac(x_q, x_r, A)[0].t  ≈ truth.t  # doctest: +SKIP
    """
    if not max_imbalance >= 0.0:
        raise InputError(f"max_imbalance: expected a number >= 0, got {max_imbalance!r}")
    out = np.empty((1, 4, 3))
    n = -1
    rays = plain_float64_pair(x_query, x_ref, 1)
    plain_affine = plain_float64_pair(affine, affine, 2) if rays is not None else None
    if rays is not None and plain_affine is not None:
        n = _relposes(*rays, plain_affine[0], float(max_imbalance), out)
    if n == -1:  # not plain float64 arrays, (2,) points, or invalid: convert, or raise the message
        xq = check_rays_or_points("x_query", x_query, (3,))
        xr = check_rays_or_points("x_ref", x_ref, (3,))
        A = np.ascontiguousarray(check_array("affine", affine, (2, 2)))
        n = _relposes(xq, xr, A, float(max_imbalance), out)
    return Pose._from_buffer(out, n)


def relpose_planar_1ac_batch(
    x_query: object, x_ref: object, affine: object
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Batched :func:`relpose_planar_1ac` for M affine correspondences.

    Args:
        x_query, x_ref: (M, 3) rays (or (M, 2) normalized points) of M affine correspondences.
        affine: (M, 2, 2) local affine maps ``∂x_ref/∂x_query`` in normalized coordinates.

    Large batches run on all cores (numba ``prange``).

    Returns:
        R (M, 1, 3, 3), t (M, 1, 3) of ``ref_from_query`` (unit ``t``), valid (M, 1) bool and
        imbalance (M, 1) (NaN where invalid); invalid slots of R and t are NaN. The leading
        solution axis of length 1 matches the other batched solvers' ``(M, K, ...)`` layout.
        No solution is filtered by its imbalance: threshold it as needed.
    """
    xq = check_rays_or_points("x_query", x_query, (None, 3))
    xr = check_rays_or_points("x_ref", x_ref, (None, 3))
    A = np.ascontiguousarray(check_array("affine", affine, (None, 2, 2)))
    if not xq.shape[0] == xr.shape[0] == A.shape[0]:
        raise InputError(
            "x_query, x_ref, affine: different numbers of correspondences "
            f"({xq.shape[0]}, {xr.shape[0]}, {A.shape[0]})"
        )
    return planar_1ac_batch_unchecked(xq, xr, A)


def planar_1ac_batch_unchecked(
    xq: np.ndarray, xr: np.ndarray, A: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`relpose_planar_1ac_batch` on contiguous float64 (M, 3), (M, 3), (M, 2, 2) arrays,
    unchecked (the entry point for a RANSAC estimator)."""
    m = xq.shape[0]
    sol = np.zeros((m, 3))
    counts = np.zeros(m, dtype=np.int64)
    (_solve_batch_parallel if m >= _PARALLEL_MIN_BATCH else _solve_batch)(xq, xr, A, sol, counts)
    valid = (counts > 0)[:, None]
    R, t = planar_poses(sol[:, 0:1], sol[:, 1:2], valid)
    imbalance = sol[:, 2:3].copy()
    imbalance[~valid] = np.nan
    return R, t, valid, imbalance
