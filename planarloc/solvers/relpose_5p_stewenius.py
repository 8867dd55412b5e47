"""Calibrated relative pose from five correspondences: Stewénius' Gröbner-basis action matrix.

Convention (as everywhere in planarloc): rays ``x_query``, ``x_ref`` satisfy
``x_refᵀ E x_query = 0`` with ``E = [t]x R`` and the returned poses are ``ref_from_query``
(``x_ref ∝ R x_query + t``), ``‖t‖ = 1``.

Algorithm (H. Stewénius, C. Engels, D. Nistér, "Recent developments on direct relative
orientation", ISPRS J. Photogrammetry and Remote Sensing 60(4):284-294, 2006: the five-point
solver by a Gröbner basis and the action matrix, followed step by step):

1. Null space ``E = x X + y Y + z Z + W`` of the five epipolar constraints and the ten cubic
   constraints ``det E = 0``, ``2 E Eᵀ E − tr(E Eᵀ) E = 0`` — shared with Nistér's solver
   (:mod:`planarloc.solvers._polynomial`).
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
  ``hqr``). Reason: numba's ``np.linalg.eig`` needs complex input and costs ~150 µs per
  10 × 10 matrix, ten times the whole solver. An eigenvalue counts as real if its imaginary
  part is below 1e-10 ``max(1, |λ|)`` (rounding can split a double real root into a pair).
* Eigenvectors of the *real* eigenvalues only, from the structure of the action matrix: with
  ``b₉ = 1`` its identity rows fix ``b₀, b₁, b₂, b₆`` and the other six rows are a 6 × 5
  least-squares problem in ``b₃, b₄, b₅, b₇ = y, b₈ = z`` (:func:`action_eigenvector`),
  instead of a general 10 × 10 null-vector computation; ``x = b₆`` is the eigenvalue itself.
* Rays are scaled to unit length; the same degeneracy checks as the Nistér solver (rank < 5,
  pure rotation, tiny elimination pivot); an eigenvalue whose 6 × 5 system is rank deficient
  (two solutions with the same ``x``, or one at infinity) is skipped.
* Each root is polished by Gauss-Newton on the ten cubic constraints when its residual is
  above rounding level (:func:`planarloc.solvers._polynomial.refine_five_point_root`).
* The pose recovery is the closed form shared with the batched kernels, not the paper's.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from planarloc.geometry.essential_decomposition import (
    check_correspondence_batch,
    check_correspondences,
    mask_invalid,
    relpose_batch_kernel,
    relposes_closed_form,
)
from planarloc.geometry.pose import Pose
from planarloc.solvers._polynomial import (
    BATCH_REFINE_ITERS,
    BATCH_REFINE_RTOL,
    RANK_TOL,
    REFINE_ITERS,
    REFINE_RTOL,
    ROTATION_ONLY_TOL,
    five_point_constraints,
    five_point_nullspace,
    gauss_jordan,
    is_rotation_only,
    refine_five_point_root,
    unit_rows,
)

__all__ = ["essentials_5p_stewenius", "relpose_5p_stewenius", "relpose_5p_stewenius_batch"]

MAX_SOLUTIONS = 10
_PIVOT_TOL = 1e-12
_REAL_TOL = 1e-10


# ---- real nonsymmetric eigenvalues (1-based arrays of size (n + 1, n + 1), as in EISPACK) ---------


@njit(cache=True)
def _balance(a, n):
    """Similarity scaling by powers of 2 so that row and column norms are comparable."""
    radix = 2.0
    sqrdx = radix * radix
    done = False
    while not done:
        done = True
        for i in range(1, n + 1):
            r = 0.0
            c = 0.0
            for j in range(1, n + 1):
                if j != i:
                    c += abs(a[j, i])
                    r += abs(a[i, j])
            if c != 0.0 and r != 0.0:
                g = r / radix
                f = 1.0
                s = c + r
                while c < g:
                    f *= radix
                    c *= sqrdx
                g = r * radix
                while c > g:
                    f /= radix
                    c /= sqrdx
                if (c + r) / f < 0.95 * s:
                    done = False
                    g = 1.0 / f
                    for j in range(1, n + 1):
                        a[i, j] *= g
                    for j in range(1, n + 1):
                        a[j, i] *= f


@njit(cache=True)
def _hessenberg(a, n):
    """Reduction to upper Hessenberg form by Gaussian elimination with pivoting."""
    for m in range(2, n):
        x = 0.0
        i = m
        for j in range(m, n + 1):
            if abs(a[j, m - 1]) > abs(x):
                x = a[j, m - 1]
                i = j
        if i != m:
            for j in range(m - 1, n + 1):
                a[i, j], a[m, j] = a[m, j], a[i, j]
            for j in range(1, n + 1):
                a[j, i], a[j, m] = a[j, m], a[j, i]
        if x != 0.0:
            for i in range(m + 1, n + 1):
                y = a[i, m - 1]
                if y != 0.0:
                    y /= x
                    a[i, m - 1] = 0.0  # (EISPACK keeps the multiplier here; we do not need it)
                    for j in range(m, n + 1):
                        a[i, j] -= y * a[m, j]
                    for j in range(1, n + 1):
                        a[j, m] += y * a[j, i]


@njit(cache=True)
def _hqr(a, n, wr, wi) -> bool:
    """All eigenvalues of an upper Hessenberg matrix by the shifted double-step QR algorithm.

    EISPACK ``hqr`` (Wilkinson & Reinsch, Handbook vol. II); a is destroyed. Returns False if
    an eigenvalue needs more than 30 iterations.
    """
    anorm = 0.0
    for i in range(1, n + 1):
        for j in range(max(i - 1, 1), n + 1):
            anorm += abs(a[i, j])
    nn = n
    t = 0.0
    p = q = r = s = w = x = y = z = 0.0
    while nn >= 1:
        its = 0
        while True:
            l = nn
            while l >= 2:
                s = abs(a[l - 1, l - 1]) + abs(a[l, l])
                if s == 0.0:
                    s = anorm
                if abs(a[l, l - 1]) + s == s:
                    a[l, l - 1] = 0.0
                    break
                l -= 1
            x = a[nn, nn]
            if l == nn:  # one root found
                wr[nn] = x + t
                wi[nn] = 0.0
                nn -= 1
            else:
                y = a[nn - 1, nn - 1]
                w = a[nn, nn - 1] * a[nn - 1, nn]
                if l == nn - 1:  # two roots found
                    p = 0.5 * (y - x)
                    q = p * p + w
                    z = np.sqrt(abs(q))
                    x += t
                    if q >= 0.0:
                        z = p + (z if p >= 0.0 else -z)
                        wr[nn - 1] = wr[nn] = x + z
                        if z != 0.0:
                            wr[nn] = x - w / z
                        wi[nn - 1] = wi[nn] = 0.0
                    else:
                        wr[nn - 1] = wr[nn] = x + p
                        wi[nn - 1] = -z
                        wi[nn] = z
                    nn -= 2
                else:
                    if its == 30:
                        return False
                    if its == 10 or its == 20:  # exceptional shift
                        t += x
                        for i in range(1, nn + 1):
                            a[i, i] -= x
                        s = abs(a[nn, nn - 1]) + abs(a[nn - 1, nn - 2])
                        x = y = 0.75 * s
                        w = -0.4375 * s * s
                    its += 1
                    m = nn - 2
                    while m >= l:
                        z = a[m, m]
                        r = x - z
                        s = y - z
                        p = (r * s - w) / a[m + 1, m] + a[m, m + 1]
                        q = a[m + 1, m + 1] - z - r - s
                        r = a[m + 2, m + 1]
                        s = abs(p) + abs(q) + abs(r)
                        p /= s
                        q /= s
                        r /= s
                        if m == l:
                            break
                        u = abs(a[m, m - 1]) * (abs(q) + abs(r))
                        v = abs(p) * (abs(a[m - 1, m - 1]) + abs(z) + abs(a[m + 1, m + 1]))
                        if u + v == v:
                            break
                        m -= 1
                    for i in range(m + 2, nn + 1):
                        a[i, i - 2] = 0.0
                        if i != m + 2:
                            a[i, i - 3] = 0.0
                    for k in range(m, nn):
                        if k != m:
                            p = a[k, k - 1]
                            q = a[k + 1, k - 1]
                            r = 0.0
                            if k != nn - 1:
                                r = a[k + 2, k - 1]
                            x = abs(p) + abs(q) + abs(r)
                            if x != 0.0:
                                p /= x
                                q /= x
                                r /= x
                        s = np.sqrt(p * p + q * q + r * r)
                        if p < 0.0:
                            s = -s
                        if s != 0.0:
                            if k == m:
                                if l != m:
                                    a[k, k - 1] = -a[k, k - 1]
                            else:
                                a[k, k - 1] = -s * x
                            p += s
                            x = p / s
                            y = q / s
                            z = r / s
                            q /= p
                            r /= p
                            for j in range(k, nn + 1):
                                p = a[k, j] + q * a[k + 1, j]
                                if k != nn - 1:
                                    p += r * a[k + 2, j]
                                    a[k + 2, j] -= p * z
                                a[k + 1, j] -= p * y
                                a[k, j] -= p * x
                            mmin = nn if nn < k + 3 else k + 3
                            for i in range(l, mmin + 1):
                                p = x * a[i, k] + y * a[i, k + 1]
                                if k != nn - 1:
                                    p += z * a[i, k + 2]
                                    a[i, k + 2] -= p * r
                                a[i, k + 1] -= p * q
                                a[i, k] -= p
            if nn < 1 or l >= nn - 1:
                break
    return True


@njit(cache=True)
def real_eigenvalues(M: np.ndarray, out: np.ndarray) -> int:
    """Real eigenvalues of a square matrix (balance, Hessenberg, hqr); returns their count."""
    n = M.shape[0]
    a = np.zeros((n + 1, n + 1))
    for i in range(n):
        for j in range(n):
            a[i + 1, j + 1] = M[i, j]
    _balance(a, n)
    _hessenberg(a, n)
    wr = np.zeros(n + 1)
    wi = np.zeros(n + 1)
    if not _hqr(a, n, wr, wi):
        return 0
    count = 0
    for i in range(1, n + 1):
        if abs(wi[i]) <= _REAL_TOL * max(1.0, abs(wr[i])):
            if wi[i] != 0.0 and wi[i] < 0.0:
                continue  # a split double root: keep one of the conjugate pair
            out[count] = wr[i]
            count += 1
    return count


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


# ---- the solver ------------------------------------------------------------------------------


@njit(cache=True)
def stewenius_essentials(
    xq: np.ndarray, xr: np.ndarray, E_out: np.ndarray, refine_iters: int, refine_rtol: float
) -> int:
    """Kernel: essential matrices from (5, 3) rays; writes E_out[:n] (unit Frobenius norm)."""
    uq = unit_rows(xq)
    ur = unit_rows(xr)
    if is_rotation_only(uq, ur, ROTATION_ONLY_TOL):
        return 0
    basis = np.empty((9, 4))
    if not five_point_nullspace(uq, ur, basis, RANK_TOL):
        return 0
    C = five_point_constraints(basis)  # columns already in graded reverse lexicographic order
    G = np.empty((10, 20))
    for i in range(10):
        for j in range(20):
            G[i, j] = C[i, j]
    if not gauss_jordan(G, 10, _PIVOT_TOL, 0):
        return 0
    # action matrix of x on b = [x², xy, xz, y², yz, z², x, y, z, 1] (columns 10..19 of G)
    M = np.zeros((10, 10))
    for i in range(6):  # x·x² = x³, x·xy = x²y, x·xz = x²z, x·y² = xy², x·yz = xyz, x·z² = xz²
        for j in range(10):
            M[i, j] = -G[i, 10 + j]
    M[6, 0] = 1.0  # x·x = x²
    M[7, 1] = 1.0  # x·y = xy
    M[8, 2] = 1.0  # x·z = xz
    M[9, 6] = 1.0  # x·1 = x
    lams = np.empty(10)
    nl = real_eigenvalues(M, lams)
    v = np.empty(10)
    sol = np.empty(3)
    m = np.empty(20)
    dm = np.empty((3, 20))
    count = 0
    for s in range(nl):
        if not action_eigenvector(M, lams[s], v):
            continue
        sol[0] = v[6]  # = lams[s]
        sol[1] = v[7]
        sol[2] = v[8]
        refine_five_point_root(C, sol, refine_iters, refine_rtol, m, dm)
        norm = 0.0
        for i in range(3):
            for j in range(3):
                r = 3 * i + j
                e = sol[0] * basis[r, 0] + sol[1] * basis[r, 1] + sol[2] * basis[r, 2] + basis[r, 3]
                E_out[count, i, j] = e
                norm += e * e
        if not (np.isfinite(norm) and norm > 0.0):
            continue
        norm = 1.0 / np.sqrt(norm)
        for i in range(3):
            for j in range(3):
                E_out[count, i, j] *= norm
        count += 1
    return count


@njit(cache=True)
def _stewenius_batch(xq, xr, R, t, valid, refine_iters, refine_rtol):
    Es = np.empty((MAX_SOLUTIONS, 3, 3))
    for m in range(xq.shape[0]):
        n = stewenius_essentials(xq[m], xr[m], Es, refine_iters, refine_rtol)
        relpose_batch_kernel(Es, n, xq[m], xr[m], R[m], t[m], valid[m])


@njit(cache=True, parallel=True)
def _stewenius_batch_parallel(xq, xr, R, t, valid, refine_iters, refine_rtol):
    for m in prange(xq.shape[0]):
        Es = np.empty((MAX_SOLUTIONS, 3, 3))
        n = stewenius_essentials(xq[m], xr[m], Es, refine_iters, refine_rtol)
        relpose_batch_kernel(Es, n, xq[m], xr[m], R[m], t[m], valid[m])


def essentials_5p_stewenius(x_query: object, x_ref: object) -> list[np.ndarray]:
    """All real essential matrices consistent with five correspondences (Stewénius et al. 2006).

    Args:
        x_query: (5, 3) rays of the query camera: normalized homogeneous points ``(x, y, 1)``
            or bearing vectors (any non-zero length, any direction).
        x_ref: (5, 3) rays of the reference camera, row ``i`` matching ``x_query[i]``.

    Returns:
        Up to 10 (3, 3) essential matrices with ``x_refᵀ E x_query = 0``, unit Frobenius norm,
        sign arbitrary. No cheirality filtering. Empty for a degenerate sample (repeated points,
        pure rotation, all points on one epipolar plane).

    Raises:
        InputError: wrong shape, NaN/inf, or a zero-length ray.

    References:
        Stewénius, Engels & Nistér, ISPRS J. 2006 (Gröbner basis, action matrix); deviations in
        the module docstring.
    """
    xq, xr = check_correspondences(x_query, x_ref, rows=5)
    Es = np.empty((MAX_SOLUTIONS, 3, 3))
    n = stewenius_essentials(xq, xr, Es, REFINE_ITERS, REFINE_RTOL)
    return [Es[i].copy() for i in range(n)]


def relpose_5p_stewenius(x_query: object, x_ref: object) -> list[Pose]:
    """All relative poses from five (or more) correspondences, Stewénius' five-point method.

    Args:
        x_query: (N ≥ 5, 3) rays of the query camera (normalized homogeneous points or
            bearings). Only the **first five** rows enter the minimal solve.
        x_ref: (N, 3) matching rays of the reference camera.

    Returns:
        ``ref_from_query`` poses (``x_ref ∝ R x_query + t``, ``‖t‖ = 1``), one for each real
        essential matrix whose decomposition puts **all N** points in front of both cameras
        (the midpoint test of :func:`planarloc.geometry.epipolar.triangulation_depths`).
        Empty for degenerate input: repeated points, pure rotation, points at infinity
        (parallel rays), all points on one epipolar plane.

    Raises:
        InputError: wrong shape, fewer than 5 rows, NaN/inf, or a zero-length ray.

    References:
        Stewénius, Engels & Nistér, ISPRS J. 2006 (Gröbner basis, action matrix); deviations in
        the module docstring.
    """
    xq, xr = check_correspondences(x_query, x_ref, min_rows=5)
    Es = np.empty((MAX_SOLUTIONS, 3, 3))
    n = stewenius_essentials(xq[:5].copy(), xr[:5].copy(), Es, REFINE_ITERS, REFINE_RTOL)
    return relposes_closed_form(Es[:n], xq, xr)


def relpose_5p_stewenius_batch(
    x_query: object, x_ref: object, *, parallel: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stewénius' five-point solver on M samples at once (for RANSAC).

    Args:
        x_query: (M, 5, 3) query rays (normalized homogeneous points or bearings).
        x_ref: (M, 5, 3) matching reference rays.
        parallel: spread the samples over numba's threads (``numba.set_num_threads``). Off by
            default: the OpenMP/TBB thread pools are not fork-safe, so a process that later
            forks workers (``multiprocessing`` on Linux) must not have used them.

    Returns:
        R: (M, 10, 3, 3) rotations ``ref_from_query``; NaN where not valid.
        t: (M, 10, 3) unit translations; NaN where not valid.
        valid: (M, 10) bool; True for a real solution whose pose puts all five sample points in
        front of both cameras. Valid solutions are packed first: ``valid[m, :k]``.

    Raises:
        InputError: wrong shape, NaN/inf, or a zero-length ray. Degenerate samples raise
        nothing; their rows of ``valid`` are all False.

    References:
        Stewénius, Engels & Nistér, ISPRS J. 2006; pose by the closed form of
        :func:`planarloc.geometry.essential_decomposition.relpose_from_essential_kernel`.
    """
    xq, xr = check_correspondence_batch(x_query, x_ref, 5)
    M = xq.shape[0]
    R = np.full((M, MAX_SOLUTIONS, 3, 3), np.nan)
    t = np.full((M, MAX_SOLUTIONS, 3), np.nan)
    valid = np.zeros((M, MAX_SOLUTIONS), dtype=np.bool_)
    kernel = _stewenius_batch_parallel if parallel else _stewenius_batch
    kernel(xq, xr, R, t, valid, BATCH_REFINE_ITERS, BATCH_REFINE_RTOL)
    mask_invalid(R, t, valid)
    return R, t, valid
