"""The five-point polynomial system and the drivers shared by Nistér's and Stewénius' solvers.

Both five-point solvers (:mod:`planarloc.solvers.relpose_5p_nister`,
:mod:`planarloc.solvers.relpose_5p_stewenius`) differ only in how they solve the polynomial
system (their root extraction); everything else lives here (numba kernels, no public Python
API):

* **The five-point polynomial system** (Nistér 2004, Sec. 3, steps "extraction of the null
  space" and "expansion of the cubic constraints"; Stewénius et al. 2006 reuse it verbatim):
  the four-dimensional null space ``E = x X + y Y + z Z + W`` of the five epipolar
  constraints and the ten cubic constraints ``det E = 0`` and ``2 E Eᵀ E − tr(E Eᵀ) E = 0``
  as a 10 × 20 coefficient matrix over the 20 monomials of degree ≤ 3 in ``(x, y, z)``.
  Columns are in the graded reverse lexicographic order of :data:`MONOMIALS`; each solver
  names the order its elimination needs (:func:`monomial_permutation`). Also the
  degeneracy tests of a five-point sample and the Gauss-Newton polishing of a root of the
  system (:func:`refine_five_point_root`, not in either paper).
* **The solver skeleton** :func:`essentials_from_roots`: the reduced elimination template
  (:func:`five_point_template`: unit rays, degeneracy tests, null space, constraints in the
  solver's monomial order, Gauss-Jordan), then the solver's root extraction
  ``roots(A (10, 20) reduced template, sols (10, 3)) -> n`` (real roots ``(x, y, z)`` in
  ``sols[:n]``), then each root polished and turned into an essential matrix
  (:func:`store_essential`). Bound to a solver's order and roots it is that solver's essentials
  kernel ``essentials(xq (5, 3), xr (5, 3), E_out (10, 3, 3), refine_iters, refine_rtol) -> n``.
* **The drivers**, parametrised by that essentials kernel
  (inlined into each solver's compiled entry points, ``inline="always"``, so the indirection
  costs nothing and the entry points stay cacheable; passing a kernel that can raise as a
  run-time argument would make numba refuse to cache the caller):
  :func:`five_point_relposes` (a validated single call: solve, decompose, cheirality on all
  points) and :func:`five_point_batch` / :func:`five_point_sample` (the RANSAC batches).

The Python functions of both solvers (checked calls, docstrings) are written once in
:mod:`planarloc.solvers._five_point_calls`.

Univariate real roots (Sturm sequences) and real eigenvalues are generic numerics and live
in :mod:`planarloc.numerics`.

The kernels assume finite, non-zero rays unless they say they validate; they return counts or
success flags instead of raising so that a batched caller never aborts a whole batch for one
degenerate sample.

Note for developers: numba's on-disk cache (``cache=True``) does not track calls across
modules; after editing a kernel here, delete ``planarloc/solvers/__pycache__/*.nb[ic]`` so
that the solvers that inline it are recompiled.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry.essential_decomposition import relpose_batch_kernel, relposes_into
from planarloc.geometry.validation import rays_invalid
from planarloc.numerics.null_space import null_space_qr

MAX_SOLUTIONS = 10  # real solutions of the five-point problem, at most

# --------------------------------------------------------------------------------------------
# Monomials of degree <= 3 in (x, y, z), graded reverse lexicographic order (x > y > z):
#   x³ x²y x²z xy² xyz xz² y³ y²z yz² z³ | x² xy xz y² yz z² | x y z | 1
# --------------------------------------------------------------------------------------------
MONOMIALS: tuple[tuple[int, int, int], ...] = (
    (3, 0, 0), (2, 1, 0), (2, 0, 1), (1, 2, 0), (1, 1, 1),
    (1, 0, 2), (0, 3, 0), (0, 2, 1), (0, 1, 2), (0, 0, 3),
    (2, 0, 0), (1, 1, 0), (1, 0, 1), (0, 2, 0), (0, 1, 1), (0, 0, 2),
    (1, 0, 0), (0, 1, 0), (0, 0, 1),
    (0, 0, 0),
)  # fmt: skip
_INDEX = {m: i for i, m in enumerate(MONOMIALS)}


def monomial_permutation(order: list[tuple[int, int, int]]) -> np.ndarray:
    """Column indices into :data:`MONOMIALS` that list the monomials in ``order``."""
    if sorted(order) != sorted(MONOMIALS):
        raise ValueError("order must be a permutation of the 20 monomials of degree <= 3")
    return np.array([_INDEX[m] for m in order], dtype=np.int64)


# Floating-point contraction (FMA) and reassociation for the dense arithmetic kernels; never the
# no-NaN/no-inf assumptions, so finiteness tests stay meaningful.
_FASTMATH = {"contract", "reassoc"}

# Tolerances shared by both five-point solvers (documented in their docstrings).
RANK_TOL = 1e-10  # smallest |R_ii| of the QR of the unit-normalised 9x5 constraint matrix
# Gauss-Newton polishing of the roots (refine_five_point_root): single calls polish to rounding
# level; the batched RANSAC kernels only polish roots whose residual shows lost digits.
REFINE_ITERS, REFINE_RTOL = 5, 1e-15
BATCH_REFINE_ITERS, BATCH_REFINE_RTOL = 5, 1e-12
# a sample is a pure rotation if max_ij | |x_q,i · x_q,j| − |x_r,i · x_r,j| | (unit rays) is below this
ROTATION_ONLY_TOL = 1e-10
PIVOT_TOL = 1e-12  # smallest Gauss-Jordan pivot of the template, relative to its largest entry


@njit(cache=True)
def unit_rows(x: np.ndarray) -> np.ndarray:
    """(N, 3) rays scaled to unit length (rows must be non-zero)."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        n = np.sqrt(x[i, 0] ** 2 + x[i, 1] ** 2 + x[i, 2] ** 2)
        for j in range(3):
            out[i, j] = x[i, j] / n
    return out


@njit(cache=True)
def is_rotation_only(uq: np.ndarray, ur: np.ndarray, tol: float) -> bool:
    """True if unit rays ``ur`` are (up to per-ray sign) a rotation of ``uq``.

    A rotation preserves all angles between rays, so equal |Gram matrices| are necessary for
    ``x_ref ∝ R x_query``. For such a sample every ``[t]x R`` satisfies the epipolar
    constraints: the five-point system has a continuum of solutions and no isolated ones.
    """
    n = uq.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            gq = uq[i, 0] * uq[j, 0] + uq[i, 1] * uq[j, 1] + uq[i, 2] * uq[j, 2]
            gr = ur[i, 0] * ur[j, 0] + ur[i, 1] * ur[j, 1] + ur[i, 2] * ur[j, 2]
            if abs(abs(gq) - abs(gr)) > tol:
                return False
    return True


@njit(cache=True, fastmath=_FASTMATH)
def five_point_nullspace(uq: np.ndarray, ur: np.ndarray, basis: np.ndarray, rank_tol: float) -> bool:
    """Orthonormal basis of the null space of the 5 x 9 epipolar constraint matrix.

    Row ``k`` of the constraint matrix is ``kron(x_ref_k, x_query_k)`` so that it dotted with
    the row-major ``vec(E)`` gives ``x_refᵀ E x_query``. Householder QR of its 9 x 5 transpose
    (:func:`planarloc.numerics.null_space.null_space_qr`; Nistér 2004 allows QR or SVD).

    Args:
        uq, ur: (5, 3) unit rays, query and reference.
        basis: (9, 4) output; columns X, Y, Z, W.
        rank_tol: the sample is degenerate (rank < 5: repeated points, points on one
            epipolar plane, ...) if a diagonal entry of R is below this (columns have norm 1).

    Returns:
        False for a degenerate sample (``basis`` is then undefined).
    """
    At = np.empty((9, 5))
    for k in range(5):
        for i in range(3):
            for j in range(3):
                At[3 * i + j, k] = ur[k, i] * uq[k, j]
    return null_space_qr(At, basis, rank_tol)


@njit(cache=True, fastmath=_FASTMATH)
def _lin_lin(a, b, out):
    """out += a * b: linear forms over (x, y, z, 1) -> quadratic over MONOMIALS[10:20]."""
    out[0] += a[0] * b[0]
    out[1] += a[0] * b[1] + a[1] * b[0]
    out[2] += a[0] * b[2] + a[2] * b[0]
    out[3] += a[1] * b[1]
    out[4] += a[1] * b[2] + a[2] * b[1]
    out[5] += a[2] * b[2]
    out[6] += a[0] * b[3] + a[3] * b[0]
    out[7] += a[1] * b[3] + a[3] * b[1]
    out[8] += a[2] * b[3] + a[3] * b[2]
    out[9] += a[3] * b[3]


@njit(cache=True, fastmath=_FASTMATH)
def _quad_lin(q, l, out, s):
    """out += s * q * l: quadratic over MONOMIALS[10:20] times linear -> cubic over MONOMIALS.

    Generated from the monomial tables; ``tests/solvers/test_relpose_5p.py`` checks the
    resulting constraints against direct evaluation of ``E = x X + y Y + z Z + W``.
    """
    out[0] += s * (q[0] * l[0])
    out[1] += s * (q[0] * l[1] + q[1] * l[0])
    out[2] += s * (q[0] * l[2] + q[2] * l[0])
    out[3] += s * (q[1] * l[1] + q[3] * l[0])
    out[4] += s * (q[1] * l[2] + q[2] * l[1] + q[4] * l[0])
    out[5] += s * (q[2] * l[2] + q[5] * l[0])
    out[6] += s * (q[3] * l[1])
    out[7] += s * (q[3] * l[2] + q[4] * l[1])
    out[8] += s * (q[4] * l[2] + q[5] * l[1])
    out[9] += s * (q[5] * l[2])
    out[10] += s * (q[0] * l[3] + q[6] * l[0])
    out[11] += s * (q[1] * l[3] + q[6] * l[1] + q[7] * l[0])
    out[12] += s * (q[2] * l[3] + q[6] * l[2] + q[8] * l[0])
    out[13] += s * (q[3] * l[3] + q[7] * l[1])
    out[14] += s * (q[4] * l[3] + q[7] * l[2] + q[8] * l[1])
    out[15] += s * (q[5] * l[3] + q[8] * l[2])
    out[16] += s * (q[6] * l[3] + q[9] * l[0])
    out[17] += s * (q[7] * l[3] + q[9] * l[1])
    out[18] += s * (q[8] * l[3] + q[9] * l[2])
    out[19] += s * (q[9] * l[3])


@njit(cache=True, fastmath=_FASTMATH)
def five_point_constraints(basis: np.ndarray) -> np.ndarray:
    """The ten cubic constraints on ``E = x X + y Y + z Z + W`` (Nistér 2004, Sec. 3).

    Rows 0-8: entries (row-major) of ``2 E Eᵀ E − tr(E Eᵀ) E``; row 9: ``det E``.

    Args:
        basis: (9, 4) null-space basis, columns X, Y, Z, W as row-major ``vec(E)``; row
            ``3 i + j`` is the linear form of ``E[i, j]`` over ``(x, y, z, 1)``.

    Returns:
        (10, 20) coefficients over :data:`MONOMIALS` (graded reverse lexicographic order).
    """
    L = basis
    EEt = np.zeros((9, 10))  # (E Eᵀ)[i, j], quadratic
    for i in range(3):
        for j in range(i, 3):
            for k in range(3):
                _lin_lin(L[3 * i + k], L[3 * j + k], EEt[3 * i + j])
            if j != i:
                for c in range(10):
                    EEt[3 * j + i, c] = EEt[3 * i + j, c]
    tr = np.empty(10)
    for c in range(10):
        tr[c] = EEt[0, c] + EEt[4, c] + EEt[8, c]
    A = np.zeros((10, 20))
    for i in range(3):
        for j in range(3):
            row = A[3 * i + j]
            for k in range(3):
                _quad_lin(EEt[3 * i + k], L[3 * k + j], row, 2.0)
            _quad_lin(tr, L[3 * i + j], row, -1.0)
    # det E = sum_k E[0, k] cof[k], cofactors of the first row
    cof = np.zeros((3, 10))
    neg = np.empty(4)
    for k in range(3):
        a = (k + 1) % 3
        b = (k + 2) % 3
        _lin_lin(L[3 + a], L[6 + b], cof[k])
        for c in range(4):
            neg[c] = -L[3 + b, c]
        _lin_lin(neg, L[6 + a], cof[k])
        _quad_lin(cof[k], L[k], A[9], 1.0)
    return A


@njit(cache=True)
def _monomials_and_jacobian(x, y, z, m, dm):
    """m[i] = MONOMIALS[i](x, y, z); dm[v, i] = d MONOMIALS[i] / d (x, y, z)[v]."""
    xx, xy, xz, yy, yz, zz = x * x, x * y, x * z, y * y, y * z, z * z
    m[0], m[1], m[2], m[3], m[4] = xx * x, xx * y, xx * z, xy * y, xy * z
    m[5], m[6], m[7], m[8], m[9] = xz * z, yy * y, yy * z, yz * z, zz * z
    m[10], m[11], m[12], m[13], m[14], m[15] = xx, xy, xz, yy, yz, zz
    m[16], m[17], m[18], m[19] = x, y, z, 1.0
    for v in range(3):
        for k in range(20):
            dm[v, k] = 0.0
    dm[0, 0], dm[0, 1], dm[0, 2], dm[0, 3], dm[0, 4], dm[0, 5] = 3 * xx, 2 * xy, 2 * xz, yy, yz, zz
    dm[0, 10], dm[0, 11], dm[0, 12], dm[0, 16] = 2 * x, y, z, 1.0
    dm[1, 1], dm[1, 3], dm[1, 4], dm[1, 6], dm[1, 7], dm[1, 8] = xx, 2 * xy, xz, 3 * yy, 2 * yz, zz
    dm[1, 11], dm[1, 13], dm[1, 14], dm[1, 17] = x, 2 * y, z, 1.0
    dm[2, 2], dm[2, 4], dm[2, 5], dm[2, 7], dm[2, 8], dm[2, 9] = xx, xy, 2 * xz, yy, 2 * yz, 3 * zz
    dm[2, 12], dm[2, 14], dm[2, 15], dm[2, 18] = x, y, 2 * z, 1.0


@njit(cache=True, fastmath=_FASTMATH)
def _residual(C, m) -> float:
    ss = 0.0
    for i in range(10):
        acc = 0.0
        for k in range(20):
            acc += C[i, k] * m[k]
        ss += acc * acc
    return ss


@njit(cache=True)
def refine_five_point_root(
    C: np.ndarray, sol: np.ndarray, iters: int, rtol: float, m: np.ndarray, dm: np.ndarray
) -> None:
    """Gauss-Newton polishing of a root (x, y, z) of the ten cubic constraints, in place.

    Not in either paper: the elimination steps lose digits on ill-conditioned samples (the
    constraints' residual at a root is then ~1e-8 instead of ~1e-16). Each step solves the
    3 x 3 normal equations of the 10 x 3 Jacobian; a step that does not reduce the residual is
    rejected, so the refinement can only improve the root. Roots whose residual is already
    below ``rtol`` times the magnitude of its terms cost one evaluation.

    Args:
        C: (10, 20) constraints over :data:`MONOMIALS` from :func:`five_point_constraints`.
        sol: (3,) root (x, y, z), refined in place.
        iters: maximum number of Gauss-Newton steps.
        rtol: stop once ``‖residual‖ ≤ rtol Σ|terms|``.
        m, dm: (20,) and (3, 20) work buffers.
    """
    _monomials_and_jacobian(sol[0], sol[1], sol[2], m, dm)
    ss = 0.0
    mag = 0.0  # magnitude of the terms: a residual at that level times 1e-12 is final
    for i in range(10):
        acc = 0.0
        for k in range(20):
            v = C[i, k] * m[k]
            acc += v
            mag += abs(v)
        ss += acc * acc
    for _ in range(iters):
        if ss <= (rtol * mag) ** 2:
            return
        # normal equations (JᵀJ) d = Jᵀ r, accumulated row by row, solved by Cramer's rule
        a00 = a01 = a02 = a11 = a12 = a22 = g0 = g1 = g2 = 0.0
        for i in range(10):
            r = j0 = j1 = j2 = 0.0
            for k in range(20):
                c = C[i, k]
                r += c * m[k]
                j0 += c * dm[0, k]
                j1 += c * dm[1, k]
                j2 += c * dm[2, k]
            a00 += j0 * j0
            a01 += j0 * j1
            a02 += j0 * j2
            a11 += j1 * j1
            a12 += j1 * j2
            a22 += j2 * j2
            g0 += j0 * r
            g1 += j1 * r
            g2 += j2 * r
        c00 = a11 * a22 - a12 * a12
        c01 = a12 * a02 - a01 * a22
        c02 = a01 * a12 - a11 * a02
        det = a00 * c00 + a01 * c01 + a02 * c02
        if not abs(det) > 1e-300:
            return
        c11 = a00 * a22 - a02 * a02
        c12 = a02 * a01 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        nx = sol[0] - (c00 * g0 + c01 * g1 + c02 * g2) / det
        ny = sol[1] - (c01 * g0 + c11 * g1 + c12 * g2) / det
        nz = sol[2] - (c02 * g0 + c12 * g1 + c22 * g2) / det
        _monomials_and_jacobian(nx, ny, nz, m, dm)
        ss_new = _residual(C, m)
        if not ss_new < ss:
            return
        sol[0], sol[1], sol[2] = nx, ny, nz
        ss = ss_new


@njit(cache=True)
def store_essential(
    C: np.ndarray,
    basis: np.ndarray,
    sol: np.ndarray,
    refine_iters: int,
    refine_rtol: float,
    m: np.ndarray,
    dm: np.ndarray,
    E_out: np.ndarray,
    count: int,
) -> int:
    """Polish the root ``sol`` (3,) of the constraints C (:func:`refine_five_point_root`), then
    write ``E = x B₀ + y B₁ + z B₂ + B₃`` (``basis`` (9, 4), row-major E) with unit Frobenius
    norm into ``E_out[count]``. Returns ``count + 1``, or ``count`` when E is zero or not
    finite (the slot is then overwritten by the next root). ``m`` (20,), ``dm`` (3, 20): scratch."""
    refine_five_point_root(C, sol, refine_iters, refine_rtol, m, dm)
    norm = 0.0
    for i in range(3):
        for j in range(3):
            r = 3 * i + j
            v = sol[0] * basis[r, 0] + sol[1] * basis[r, 1] + sol[2] * basis[r, 2] + basis[r, 3]
            E_out[count, i, j] = v
            norm += v * v
    if not (np.isfinite(norm) and norm > 0.0):
        return count
    norm = 1.0 / np.sqrt(norm)
    for i in range(3):
        for j in range(3):
            E_out[count, i, j] *= norm
    return count + 1


@njit(cache=True, fastmath=_FASTMATH)
def gauss_jordan(A: np.ndarray, ncols: int, pivot_tol: float, first_row: int) -> bool:
    """In-place Gauss-Jordan elimination with partial pivoting of the first ``ncols`` columns.

    Forward elimination with partial pivoting, then back substitution restricted to the rows
    ``first_row:`` (the rows above are left in echelon form; ``first_row = 0`` is the full
    reduction). On success ``A[first_row:, :ncols]`` is ``[0 | I]`` (``A`` has ``ncols`` rows).
    Returns False if a pivot falls below ``pivot_tol`` times the largest entry.
    """
    n = A.shape[0]
    m = A.shape[1]
    scale = 0.0
    for i in range(n):
        for j in range(m):
            scale = max(scale, abs(A[i, j]))
    if scale == 0.0:
        return False
    for c in range(ncols):
        p = c
        for r in range(c + 1, n):
            if abs(A[r, c]) > abs(A[p, c]):
                p = r
        if abs(A[p, c]) <= pivot_tol * scale:
            return False
        if p != c:
            for j in range(c, m):
                tmp = A[c, j]
                A[c, j] = A[p, j]
                A[p, j] = tmp
        inv = 1.0 / A[c, c]
        for r in range(c + 1, n):
            f = A[r, c] * inv
            if f != 0.0:
                for j in range(c + 1, m):
                    A[r, j] -= f * A[c, j]
            A[r, c] = 0.0
    for c in range(ncols - 1, first_row - 1, -1):
        inv = 1.0 / A[c, c]
        for j in range(ncols, m):
            A[c, j] *= inv
        A[c, c] = 1.0
        for r in range(first_row, c):
            f = A[r, c]
            if f != 0.0:
                for j in range(ncols, m):
                    A[r, j] -= f * A[c, j]
                A[r, c] = 0.0
    return True


# --------------------------------------------------------------------------------------------
# The solver skeleton shared by both solvers, parametrised by the root extraction
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def five_point_template(
    xq: np.ndarray,
    xr: np.ndarray,
    columns: np.ndarray,
    first_row: int,
    basis: np.ndarray,
    C: np.ndarray,
    A: np.ndarray,
) -> bool:
    """The reduced elimination template of a (5, 3) ray sample, the part both solvers share.

    Rays scaled to unit length; a pure-rotation sample (:func:`is_rotation_only`, tolerance
    ``ROTATION_ONLY_TOL``) or a rank-deficient one (:func:`five_point_nullspace`, ``RANK_TOL``)
    is rejected. Writes the null-space basis into ``basis`` (9, 4), the ten cubic constraints
    (:func:`five_point_constraints`, columns in :data:`MONOMIALS` order) into ``C`` (10, 20) and
    into ``A`` (10, 20) the same constraints with column ``j`` taken from ``C[:, columns[j]]``
    (the solver's monomial order), reduced by :func:`gauss_jordan` of the ten cubic columns with
    back substitution from row ``first_row`` (pivots below ``PIVOT_TOL``).

    Returns:
        False for a degenerate sample (the outputs are then undefined).
    """
    uq = unit_rows(xq)
    ur = unit_rows(xr)
    if is_rotation_only(uq, ur, ROTATION_ONLY_TOL):
        return False
    if not five_point_nullspace(uq, ur, basis, RANK_TOL):
        return False
    constraints = five_point_constraints(basis)
    # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
    for i in range(10):
        for j in range(20):
            C[i, j] = constraints[i, j]
    for i in range(10):
        for j in range(20):
            A[i, j] = C[i, columns[j]]
    return gauss_jordan(A, 10, PIVOT_TOL, first_row)


@njit(cache=True, inline="always")
def essentials_from_roots(roots, columns, first_row, xq, xr, E_out, refine_iters, refine_rtol) -> int:
    """A solver's essentials kernel: essential matrices of (5, 3) rays into ``E_out[:n]`` (unit
    Frobenius norm), returning n.

    The template of :func:`five_point_template` (monomial order ``columns``, back substitution
    from ``first_row``), then the solver's ``roots(A, sols) -> k`` (module docstring), then each
    root polished and turned into ``E = x X + y Y + z Z + W`` (:func:`store_essential`).
    """
    basis = np.empty((9, 4))
    C = np.empty((10, 20))
    A = np.empty((10, 20))
    if not five_point_template(xq, xr, columns, first_row, basis, C, A):
        return 0
    sols = np.empty((MAX_SOLUTIONS, 3))
    k = roots(A, sols)
    m = np.empty(20)
    dm = np.empty((3, 20))
    count = 0
    for s in range(k):
        count = store_essential(C, basis, sols[s], refine_iters, refine_rtol, m, dm, E_out, count)
    return count


# --------------------------------------------------------------------------------------------
# Drivers shared by both solvers, parametrised by the essentials kernel; single calls polish
# the roots with (REFINE_ITERS, REFINE_RTOL), the RANSAC batches with the BATCH_ pair
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def five_point_essentials(essentials, xq, xr, E_out) -> int:
    """Validated single call of an essentials kernel on (5, 3) rays; -1 for invalid input.

    Invalid: not (5, 3), NaN/inf, or an all-zero ray (the conditions of
    :func:`planarloc.geometry.essential_decomposition.check_correspondences`, which the Python
    API then calls for the error message). Otherwise the number of matrices in ``E_out``.
    """
    if rays_invalid(xq, xr, 5, 5, True):
        return -1
    return essentials(xq, xr, E_out, REFINE_ITERS, REFINE_RTOL)


@njit(cache=True, inline="always")
def five_point_relposes(essentials, xq, xr, out) -> int:
    """Validated single call: poses from the first five of N ≥ 5 matches, cheirality on all N.

    Args:
        essentials: the solver's essentials kernel (see the module docstring).
        xq, xr: (N, 3) query / reference rays, any float64 input (validated here).
        out: (10, 4, 3) output; pose k is ``R = out[k, :3]``, ``t = out[k, 3]``.

    Returns:
        -1 for invalid input (shape, fewer than 5 rows, NaN/inf, a zero ray), else the number
        of poses written.
    """
    if rays_invalid(xq, xr, -1, 5, True):
        return -1
    q5 = np.empty((5, 3))
    r5 = np.empty((5, 3))
    for i in range(5):
        for j in range(3):
            q5[i, j] = xq[i, j]
            r5[i, j] = xr[i, j]
    Es = np.empty((MAX_SOLUTIONS, 3, 3))
    n = essentials(q5, r5, Es, REFINE_ITERS, REFINE_RTOL)
    return relposes_into(Es, n, xq, xr, out)


@njit(cache=True, inline="always")
def five_point_sample(essentials, xq, xr, Es, R, t, valid) -> int:
    """One RANSAC sample: essentials of (5, 3) rays, then the poses passing cheirality on all
    five, packed into R (10, 3, 3), t (10, 3), valid (10,). ``Es`` is a (10, 3, 3) scratch
    buffer. Returns the number of poses."""
    n = essentials(xq, xr, Es, BATCH_REFINE_ITERS, BATCH_REFINE_RTOL)
    return relpose_batch_kernel(Es, n, xq, xr, R, t, valid)


@njit(cache=True, inline="always")
def five_point_batch(essentials, xq, xr, R, t, valid) -> None:
    """:func:`five_point_sample` over M samples: xq, xr (M, 5, 3); R (M, 10, 3, 3), t (M, 10, 3),
    valid (M, 10). The parallel twin of a solver is a ``prange`` loop over
    :func:`five_point_sample` in its own module (a parallel kernel is cached only if it is
    the outermost compiled function)."""
    Es = np.empty((MAX_SOLUTIONS, 3, 3))
    for m in range(xq.shape[0]):
        five_point_sample(essentials, xq[m], xr[m], Es, R[m], t[m], valid[m])
