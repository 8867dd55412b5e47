"""Calibrated relative pose from five correspondences: Stewénius' Gröbner-basis action matrix.

Convention (as everywhere in planarloc): rays ``x_query``, ``x_ref`` satisfy
``x_refᵀ E x_query = 0`` with ``E = [t]x R`` and the returned poses are ``ref_from_query``
(``x_ref ∝ R x_query + t``), ``‖t‖ = 1``.

Algorithm (H. Stewénius, C. Engels, D. Nistér, "Recent developments on direct relative
orientation", ISPRS J. Photogrammetry and Remote Sensing 60(4):284-294, 2006: the five-point
solver by a Gröbner basis and the action matrix, followed step by step):

1. Null space ``E = x X + y Y + z Z + W`` of the five epipolar constraints and the ten cubic
   constraints ``det E = 0``, ``2 E Eᵀ E − tr(E Eᵀ) E = 0`` — shared with Nistér's solver
   (:mod:`planarloc.solvers._five_point`).
2. The 10 × 20 *elimination template*: the constraint coefficients with the monomials in graded
   reverse lexicographic order ``x³ x²y x²z xy² xyz xz² y³ y²z yz² z³ | x² xy xz y² yz z² x y z 1``.
   Gauss-Jordan elimination (partial pivoting) of the ten cubic columns gives the reduced
   Gröbner basis: every cubic monomial expressed in the quotient-ring basis
   ``b = [x², xy, xz, y², yz, z², x, y, z, 1]``.
3. The 10 × 10 *action matrix* of multiplication by ``x`` on that basis: ``x·b = M b`` — rows
   0-5 are minus the reduced rows of ``x³, x²y, x²z, xy², xyz, xz²``, rows 6-9 pick
   ``x·x = x², x·y = xy, x·z = xz, x·1 = x``.
4. *Eigen-decomposition*: each solution is a right eigenvector ``M b(x, y, z) = x b(x, y, z)``;
   real eigenvalues give real solutions, read off as ``x = b₆/b₉, y = b₇/b₉, z = b₈/b₉``.
5. ``E = x X + y Y + z Z + W``; the pose from the decomposition and cheirality of
   :mod:`planarloc.geometry.essential_decomposition`.

Unlike Nistér's solver (hidden variable ``z``, tenth-degree polynomial, Sturm sequences) no
univariate polynomial is formed: all three unknowns come from the eigenvectors.

Deviations from the paper:

* Eigenvalues by our own numba port of the classic EISPACK/Numerical Recipes route
  (balancing, reduction to Hessenberg form by stabilised elimination, shifted double-step QR,
  ``hqr``; :func:`planarloc.numerics.eigen.real_eigenvalues`). Reason: numba's
  ``np.linalg.eig`` needs complex input and costs ~150 µs per 10 × 10 matrix, ten times the
  whole solver. An eigenvalue counts as real if its imaginary
  part is below 1e-10 ``max(1, |λ|)`` (rounding can split a double real root into a pair).
* Eigenvectors of the *real* eigenvalues only, from the structure of the action matrix: with
  ``b₉ = 1`` its identity rows fix ``b₀, b₁, b₂, b₆`` and the other six rows are a 6 × 5
  least-squares problem in ``b₃, b₄, b₅, b₇ = y, b₈ = z`` (:func:`action_eigenvector`),
  instead of a general 10 × 10 null-vector computation; ``x = b₆`` is the eigenvalue itself.
* Rays are scaled to unit length; the same degeneracy checks as the Nistér solver (rank < 5,
  pure rotation, tiny elimination pivot); an eigenvalue whose 6 × 5 system is rank deficient
  (two solutions with the same ``x``, or one at infinity) is skipped.
* Each root is polished by Gauss-Newton on the ten cubic constraints when its residual is
  above rounding level (:func:`planarloc.solvers._five_point.refine_five_point_root`).
* The pose recovery is the closed form shared with the batched kernels, not the paper's.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from planarloc.numerics.eigen import real_eigenvalues
from planarloc.solvers._five_point import (
    MAX_SOLUTIONS,
    essentials_from_roots,
    five_point_batch,
    five_point_essentials,
    five_point_relposes,
    five_point_sample,
)
from planarloc.solvers._five_point_calls import FivePointCalls

__all__ = [
    "essentials_5p_stewenius",
    "relpose_5p_stewenius",
    "relpose_5p_stewenius_batch",
    "relpose_5p_stewenius_batch_unchecked",
]

_GREVLEX = np.arange(20)  # the template keeps the constraints' graded reverse lexicographic order


@njit(cache=True)
def action_eigenvector(M: np.ndarray, lam: float, v: np.ndarray) -> bool:
    """Eigenvector ``b = [x², xy, xz, y², yz, z², x, y, z, 1]`` of the action matrix for x = lam.

    ``(M − lam I) b = 0`` with ``b₉ = 1``: rows 6-9 (the identity rows of M) give
    ``b₆ = lam, b₀ = lam², b₁ = lam b₇, b₂ = lam b₈``; rows 0-5 are then six consistent linear
    equations in the five unknowns ``b₃, b₄, b₅, b₇, b₈``, solved in the least-squares sense
    by Householder QR. This is the null vector of ``M − lam I`` restricted to the
    normalisation ``b₉ = 1`` (solutions at infinity, ``b₉ = 0``, are not representable).

    Returns False if the 6 x 5 system is rank deficient (two solutions share x).
    """
    A = np.empty((6, 6))  # [coefficients | right-hand side]
    l2 = lam * lam
    for i in range(6):
        A[i, 0] = M[i, 3]
        A[i, 1] = M[i, 4]
        A[i, 2] = M[i, 5]
        A[i, 3] = lam * M[i, 1] + M[i, 7]
        A[i, 4] = lam * M[i, 2] + M[i, 8]
        A[i, 5] = -(M[i, 0] * l2 + M[i, 6] * lam + M[i, 9])
    A[0, 5] += l2 * lam  # row 0: lam b₀ = lam³
    A[1, 3] -= l2  # row 1: lam b₁ = lam² b₇
    A[2, 4] -= l2  # row 2: lam b₂ = lam² b₈
    A[3, 0] -= lam  # rows 3-5: lam b₃, lam b₄, lam b₅
    A[4, 1] -= lam
    A[5, 2] -= lam
    scale = 0.0
    for i in range(6):
        for j in range(5):
            scale = max(scale, abs(A[i, j]))
    # Householder QR of the 6 x 5 coefficients, applied to the right-hand side as well
    for k in range(5):
        norm = 0.0
        for i in range(k, 6):
            norm += A[i, k] * A[i, k]
        norm = np.sqrt(norm)
        if not norm > 1e-12 * scale:
            return False
        alpha = -norm if A[k, k] >= 0.0 else norm
        v0 = A[k, k] - alpha
        vn = v0 * v0
        for i in range(k + 1, 6):
            vn += A[i, k] * A[i, k]
        A[k, k] = v0  # Householder vector in A[k:, k] during the update
        for j in range(k + 1, 6):
            dot = 0.0
            for i in range(k, 6):
                dot += A[i, k] * A[i, j]
            f = 2.0 * dot / vn
            for i in range(k, 6):
                A[i, j] -= f * A[i, k]
        A[k, k] = alpha
    w = np.empty(5)
    for k in range(4, -1, -1):
        acc = A[k, 5]
        for j in range(k + 1, 5):
            acc -= A[k, j] * w[j]
        w[k] = acc / A[k, k]
    v[0], v[1], v[2] = l2, lam * w[3], lam * w[4]
    v[3], v[4], v[5] = w[0], w[1], w[2]
    v[6], v[7], v[8], v[9] = lam, w[3], w[4], 1.0
    return True


@njit(cache=True)
def stewenius_roots(A: np.ndarray, sols: np.ndarray) -> int:
    """Steps 3-4: the real roots ``(x, y, z)`` of the fully reduced template ``A`` (10, 20) (the
    reduced Gröbner basis) from the action matrix of x, into ``sols[:n]`` (10, 3); returns n."""
    # action matrix of x on b = [x², xy, xz, y², yz, z², x, y, z, 1] (columns 10..19 of A)
    M = np.zeros((10, 10))
    for i in range(6):  # x·x² = x³, x·xy = x²y, x·xz = x²z, x·y² = xy², x·yz = xyz, x·z² = xz²
        for j in range(10):
            M[i, j] = -A[i, 10 + j]
    M[6, 0] = 1.0  # x·x = x²
    M[7, 1] = 1.0  # x·y = xy
    M[8, 2] = 1.0  # x·z = xz
    M[9, 6] = 1.0  # x·1 = x
    lams = np.empty(10)
    nl = real_eigenvalues(M, lams)
    v = np.empty(10)
    count = 0
    for s in range(nl):
        if not action_eigenvector(M, lams[s], v):
            continue
        sols[count, 0] = v[6]  # = lams[s]
        sols[count, 1] = v[7]
        sols[count, 2] = v[8]
        count += 1
    return count


@njit(cache=True)
def stewenius_essentials(
    xq: np.ndarray, xr: np.ndarray, E_out: np.ndarray, refine_iters: int, refine_rtol: float
) -> int:
    """Kernel: essential matrices from (5, 3) rays; writes E_out[:n] (unit Frobenius norm)."""
    return essentials_from_roots(stewenius_roots, _GREVLEX, 0, xq, xr, E_out, refine_iters, refine_rtol)


# ---- the shared five-point drivers bound to this solver's kernel --------------------------------


@njit(cache=True)
def _essentials(xq, xr, E_out):
    return five_point_essentials(stewenius_essentials, xq, xr, E_out)


@njit(cache=True)
def _relposes(xq, xr, out):
    return five_point_relposes(stewenius_essentials, xq, xr, out)


@njit(cache=True)
def _batch(xq, xr, R, t, valid):
    five_point_batch(stewenius_essentials, xq, xr, R, t, valid)


@njit(cache=True, parallel=True)
def _batch_parallel(xq, xr, R, t, valid):
    for m in prange(xq.shape[0]):
        Es = np.empty((MAX_SOLUTIONS, 3, 3))
        five_point_sample(stewenius_essentials, xq[m], xr[m], Es, R[m], t[m], valid[m])


# ---- the public functions, written once in _five_point_calls ------------------------------------

(
    essentials_5p_stewenius,
    relpose_5p_stewenius,
    relpose_5p_stewenius_batch,
    relpose_5p_stewenius_batch_unchecked,
) = FivePointCalls(_essentials, _relposes, _batch, _batch_parallel).public_functions(
    __name__,
    "stewenius",
    solver="Stewénius' five-point",
    citation="Stewénius et al. 2006",
    references=(
        "Stewénius, Engels & Nistér, ISPRS J. 2006 (Gröbner basis, action matrix); deviations in the"
        " module docstring"
    ),
)
