"""Calibrated relative pose from eight or more correspondences: the normalized 8-point method.

Convention (as everywhere in planarloc): rays ``x_query``, ``x_ref`` satisfy
``x_refᵀ E x_query = 0`` with ``E = [t]x R`` and the returned poses are ``ref_from_query``
(``x_ref ∝ R x_query + t``), ``‖t‖ = 1``.

Algorithm (R. Hartley, "In defense of the eight-point algorithm", IEEE TPAMI 19(6), 1997;
Hartley & Zisserman, 2nd ed., Algorithm 11.1 with Sec. 9.6 for the calibrated case):

1. *Normalization*: dehomogenise ``(x/z, y/z)``, translate the centroid to the origin and scale
   the mean distance to ``√2``, separately in each image (``x̂ = T x``).
2. *Linear solution*: ``vec(Ê)`` is the right singular vector of the smallest singular value
   of the N × 9 matrix with rows ``kron(x̂_ref, x̂_query)``.
3. *Constraint enforcement*: ``E = T_refᵀ Ê T_query`` is projected onto the essential manifold,
   ``E = U diag(1, 1, 0) Vᵀ`` (H&Z Sec. 9.6.1; the paper's rank-2 projection for F keeps σ1 ≠ σ2).
4. *Pose*: the decomposition that puts all N points in front of both cameras
   (:mod:`planarloc.geometry.essential_decomposition`).

Deviations:

* Normalization needs ``z ≠ 0``. If any ray has ``|z| < 0.1 ‖x‖`` (more than ~84° off the
  optical axis, as wide-angle bearings can be) the rays are instead scaled to unit length,
  which is isotropic enough for the linear step.
* Degenerate input gives no solution instead of an arbitrary one: the second-smallest singular
  value of the design matrix below 1e-10 of the largest (null space of dimension ≥ 2: fewer
  than 8 distinct correspondences, all points on a plane — a critical surface of the 8-point
  method — or pure rotation), or a projected ``E`` of rank < 2.
* The batched kernel takes the null vector from a Householder QR of the 9 × 8 transposed
  design matrix (exactly eight points) with the same 1e-10 rank test on its diagonal.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.essential_decomposition import (
    check_correspondence_batch,
    relpose_from_essential_kernel,
    relposes_closed_form,
    solve_correspondences,
    solve_relpose_batch,
)
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import rays_invalid
from planarloc.numerics.null_space import null_space_qr

__all__ = ["essential_8p", "relpose_8p", "relpose_8p_batch", "relpose_8p_batch_unchecked"]

RANK_TOL = 1e-10
MIN_COS_OPTICAL_AXIS = 0.1  # |z| / ‖x‖ below this for any ray: no Hartley normalization


@njit(cache=True)
def _normalize(x, out, T) -> bool:
    """Hartley normalization of the rays x (N, 3) into out; T (3, 3) with out = (T x)ᵀ.

    Falls back to unit-length rays (T = I) when a ray is far from the optical axis.
    Returns False if all points coincide (no scale).
    """
    n = x.shape[0]
    hartley = True
    for i in range(n):
        norm = np.sqrt(x[i, 0] ** 2 + x[i, 1] ** 2 + x[i, 2] ** 2)
        if not abs(x[i, 2]) >= MIN_COS_OPTICAL_AXIS * norm:
            hartley = False
    for i in range(3):
        for j in range(3):
            T[i, j] = 0.0
    if not hartley:
        T[0, 0] = T[1, 1] = T[2, 2] = 1.0
        for i in range(n):
            norm = np.sqrt(x[i, 0] ** 2 + x[i, 1] ** 2 + x[i, 2] ** 2)
            for j in range(3):
                out[i, j] = x[i, j] / norm
        return True
    cx = cy = 0.0
    for i in range(n):
        cx += x[i, 0] / x[i, 2]
        cy += x[i, 1] / x[i, 2]
    cx /= n
    cy /= n
    d = 0.0
    for i in range(n):
        d += np.sqrt((x[i, 0] / x[i, 2] - cx) ** 2 + (x[i, 1] / x[i, 2] - cy) ** 2)
    d /= n
    if not d > 0.0:
        return False
    s = np.sqrt(2.0) / d
    T[0, 0] = T[1, 1] = s
    T[0, 2] = -s * cx
    T[1, 2] = -s * cy
    T[2, 2] = 1.0
    for i in range(n):
        out[i, 0] = s * (x[i, 0] / x[i, 2] - cx)
        out[i, 1] = s * (x[i, 1] / x[i, 2] - cy)
        out[i, 2] = 1.0
    return True


@njit(cache=True)
def _denormalize(En, Tq, Tr, E):
    """E = Trᵀ En Tq."""
    C = m3.t_mul(Tr, m3.mul(En, Tq))
    for i in range(3):  # by element: a slice assignment compiles numba's shape-error overloads
        for j in range(3):
            E[i, j] = C[i, j]


@njit(cache=True)
def _null_vector_8(A, e) -> bool:
    """Null vector ``e`` (9, 1) of the 8 x 9 matrix A by Householder QR of Aᵀ (rows of A scaled to
    unit length first)."""
    At = np.empty((9, 8))
    for k in range(8):
        norm = 0.0
        for j in range(9):
            norm += A[k, j] * A[k, j]
        norm = np.sqrt(norm)
        if not norm > 0.0:
            return False
        for j in range(9):
            At[j, k] = A[k, j] / norm
    return null_space_qr(At, e, RANK_TOL)


@njit(cache=True)
def _scratch_8p():
    """Work buffers of :func:`_solve_8p` (allocated once per batch)."""
    return (
        np.empty((8, 3)),
        np.empty((8, 3)),
        np.empty((3, 3)),
        np.empty((3, 3)),
        np.empty((8, 9)),
        np.empty((9, 1)),
        np.empty((3, 3)),
        np.empty((3, 3)),
        np.empty((4, 3, 3)),
    )


@njit(cache=True)
def _solve_8p(xq, xr, R, t, scratch) -> bool:
    """One sample of exactly eight matches: the pose into R (3, 3), t (3,); False if none."""
    nq, nr, Tq, Tr, A, e, En, E, work = scratch
    if not (_normalize(xq, nq, Tq) and _normalize(xr, nr, Tr)):
        return False
    for k in range(8):
        for i in range(3):
            for j in range(3):
                A[k, 3 * i + j] = nr[k, i] * nq[k, j]
    if not _null_vector_8(A, e):
        return False
    for i in range(3):
        for j in range(3):
            En[i, j] = e[3 * i + j, 0]
    _denormalize(En, Tq, Tr, E)
    for i in range(3):
        for j in range(3):
            if not np.isfinite(E[i, j]):
                return False
    U, S, Vt = np.linalg.svd(E)
    if not S[1] > RANK_TOL * S[0]:
        return False
    for i in range(3):
        for j in range(3):
            E[i, j] = U[i, 0] * Vt[0, j] + U[i, 1] * Vt[1, j]
    return relpose_from_essential_kernel(E, xq, xr, R, t, work)


@njit(cache=True)
def _batch_8p(xq, xr, R, t, valid):
    scratch = _scratch_8p()
    for m in range(xq.shape[0]):
        valid[m, 0] = _solve_8p(xq[m], xr[m], R[m, 0], t[m, 0], scratch)


@njit(cache=True)
def _validate(xq, xr, out) -> int:
    """-1 for invalid input (as :func:`_relpose_8p_minimal`), else 0; ``out`` is unused."""
    return -1 if rays_invalid(xq, xr, -1, 8, True) else 0


@njit(cache=True)
def _relpose_8p_minimal(xq, xr, out) -> int:
    """Validated single call: -1 invalid input, -2 more than eight matches (not handled here),
    else the number of poses (0 or 1) written as ``out[0, :3] = R``, ``out[0, 3] = t``."""
    if rays_invalid(xq, xr, -1, 8, True):
        return -1
    if xq.shape[0] != 8:
        return -2
    R = np.empty((3, 3))
    t = np.empty(3)
    if not _solve_8p(xq, xr, R, t, _scratch_8p()):
        return 0
    for i in range(3):
        for j in range(3):
            out[0, i, j] = R[i, j]
        out[0, 3, i] = t[i]
    return 1


def essential_8p(x_query: object, x_ref: object) -> list[np.ndarray]:
    """Essential matrix from N ≥ 8 correspondences by the normalized 8-point method.

    Args:
        x_query: (N ≥ 8, 3) rays of the query camera: normalized homogeneous points
            ``(x, y, 1)`` or bearing vectors.
        x_ref: (N, 3) matching rays of the reference camera.

    Returns:
        ``[E]`` with E (3, 3), ``x_refᵀ E x_query ≈ 0`` in the least-squares sense of the
        normalized linear system, singular values ``(1/√2, 1/√2, 0)`` (unit Frobenius norm),
        sign arbitrary; ``[]`` for degenerate input (see module docstring). A list, like every
        solver of planarloc, although there is at most one solution.

    Raises:
        InputError: wrong shape, fewer than 8 rows, NaN/inf, or a zero-length ray.

    References:
        Hartley, TPAMI 1997; Hartley & Zisserman Alg. 11.1 and Sec. 9.6.1.
    """
    _, xq, xr = solve_correspondences(_validate, x_query, x_ref, None, min_rows=8)
    return _essential_8p_unchecked(xq, xr)


def _essential_8p_unchecked(xq: np.ndarray, xr: np.ndarray) -> list[np.ndarray]:
    N = xq.shape[0]
    nq, nr = np.empty((N, 3)), np.empty((N, 3))
    Tq, Tr = np.empty((3, 3)), np.empty((3, 3))
    if not (_normalize(xq, nq, Tq) and _normalize(xr, nr, Tr)):
        return []
    A = (nr[:, :, None] * nq[:, None, :]).reshape(N, 9)
    try:
        _, S, Vt = np.linalg.svd(A, full_matrices=True)
        if not S[7] > RANK_TOL * S[0]:
            return []  # null space of dimension >= 2
        E = Tr.T @ Vt[8].reshape(3, 3) @ Tq
        U, S, Vt = np.linalg.svd(E)
    except np.linalg.LinAlgError:
        return []
    if not (np.all(np.isfinite(S)) and S[1] > RANK_TOL * S[0]):
        return []
    E = U[:, :2] @ Vt[:2]  # U diag(1, 1, 0) Vᵀ
    return [E / np.sqrt(2.0)]


def relpose_8p(x_query: object, x_ref: object) -> list[Pose]:
    """Relative pose from N ≥ 8 correspondences by the normalized 8-point method.

    Args:
        x_query: (N ≥ 8, 3) rays of the query camera (normalized homogeneous points or
            bearings).
        x_ref: (N, 3) matching rays of the reference camera.

    Returns:
        The ``ref_from_query`` poses (``x_ref ∝ R x_query + t``, ``‖t‖ = 1``) of
        :func:`essential_8p` whose decomposition puts **all N** points in front of both cameras
        (the test of :func:`planarloc.geometry.essential_decomposition.relposes_from_essential`,
        run by the numba kernel shared with the batched solvers): usually one pose; ``[]`` for
        degenerate input, for points at infinity (parallel rays) and when noise or outliers put
        any point behind a camera.

    Raises:
        InputError: wrong shape, fewer than 8 rows, NaN/inf, or a zero-length ray.

    References:
        Hartley, TPAMI 1997; Hartley & Zisserman Alg. 11.1, Sec. 9.6.
    """
    out = np.empty((1, 4, 3))
    n, xq, xr = solve_correspondences(_relpose_8p_minimal, x_query, x_ref, out, min_rows=8)
    if n >= 0:  # minimal: the batch kernel (QR null vector), one compiled call
        return Pose._from_buffer(out, n)
    Es = _essential_8p_unchecked(xq, xr)  # more than eight matches (validated): SVD of the N x 9 system
    return relposes_closed_form(np.array(Es).reshape(-1, 3, 3), xq, xr)


def relpose_8p_batch(x_query: object, x_ref: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normalized 8-point method on M samples of exactly eight correspondences.

    Args:
        x_query: (M, 8, 3) query rays (normalized homogeneous points or bearings).
        x_ref: (M, 8, 3) matching reference rays.

    Returns:
        R: (M, 1, 3, 3) rotations ``ref_from_query``; NaN where not valid.
        t: (M, 1, 3) unit translations; NaN where not valid.
        valid: (M, 1) bool; True if the sample is not degenerate and the pose puts all eight
        points in front of both cameras.

    Raises:
        InputError: wrong shape, NaN/inf, or a zero-length ray.

    References:
        As :func:`relpose_8p`; null vector by Householder QR, pose by the closed form of
        :func:`planarloc.geometry.essential_decomposition.relpose_from_essential_kernel`.
    """
    return relpose_8p_batch_unchecked(*check_correspondence_batch(x_query, x_ref, 8))


def relpose_8p_batch_unchecked(xq: np.ndarray, xr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`relpose_8p_batch` on validated contiguous float64 (M, 8, 3) rays (the RANSAC
    estimators' entry point: their problem is validated once)."""
    return solve_relpose_batch(_batch_8p, xq, xr, 1)
