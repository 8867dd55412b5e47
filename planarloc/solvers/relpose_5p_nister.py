"""Calibrated relative pose from five correspondences: Nistér's tenth-degree polynomial.

Convention (as everywhere in planarloc): rays ``x_query``, ``x_ref`` satisfy
``x_refᵀ E x_query = 0`` with ``E = [t]x R`` and the returned poses are ``ref_from_query``
(``x_ref ∝ R x_query + t``), ``‖t‖ = 1``.

Algorithm (D. Nistér, "An efficient solution to the five-point relative pose problem",
IEEE TPAMI 26(6), 2004, Sec. 3 "The five-point method", followed step by step):

1. *Extraction of the null space*: the five epipolar constraints on ``vec(E)`` leave a
   four-dimensional null space ``E = x X + y Y + z Z + W`` (Householder QR here).
2. *Expansion of the cubic constraints*: ``det E = 0`` and ``2 E Eᵀ E − tr(E Eᵀ) E = 0`` give
   10 cubic equations in the 20 monomials ordered
   ``x³ y³ x²y xy² x²z x² y²z y² xyz xy | xz² xz x yz² yz y z³ z² z 1``.
3. *Gauss-Jordan elimination* (partial pivoting) of the first ten columns; the rows are the
   paper's ⟨a⟩ ... ⟨j⟩. Only ⟨e⟩ ... ⟨j⟩ are used, so the back substitution stops there
   (rows ⟨a⟩ ... ⟨d⟩ stay in echelon form).
4. *Expansion of the determinant polynomial*: ``⟨k⟩ = ⟨e⟩ − z⟨f⟩``, ``⟨l⟩ = ⟨g⟩ − z⟨h⟩``,
   ``⟨m⟩ = ⟨i⟩ − z⟨j⟩`` are linear in ``(x, y, 1)`` with coefficients of degree 3, 3, 4 in ``z``:
   ``B(z) [x, y, 1]ᵀ = 0``; ``⟨n⟩ = det B(z)`` is the tenth-degree polynomial, expanded from the
   cofactors ``p1, p2`` (degree 7) and ``p3`` (degree 6) of the last two rows.
5. *Extraction of roots*: **Sturm sequences and bisection**, as in the paper, then Newton
   polishing safeguarded by bisection. Chosen over companion-matrix eigenvalues because it
   finds only the real roots (complex ones never cost anything), needs no LAPACK call (which
   from numba costs more than the whole solver) and Stewénius' solver in
   :mod:`planarloc.solvers.relpose_5p_stewenius` already covers the eigenvalue route.
6. *Recovery*: ``x = p1(z)/p3(z)``, ``y = p2(z)/p3(z)``, ``E = x X + y Y + z Z + W``; the
   pose that passes the cheirality test of
   :func:`planarloc.geometry.essential_decomposition.relposes_from_essential`.

Deviations from the paper:

* Rays are scaled to unit length before step 1 (does not change the solution set; improves
  conditioning for wide-angle bearings).
* Each root ``(x, y, z)`` whose residual in the ten cubic constraints shows lost digits is
  polished by Gauss-Newton on those constraints
  (:func:`planarloc.solvers._five_point.refine_five_point_root`): the hidden-variable
  elimination loses up to ~6 digits on ill-conditioned samples (about 5 % of random scenes
  have errors above 1e-8 without it, none with it). Single calls polish to rounding level
  (≤ 5 steps, until the residual is 1e-15 of its terms), the batched kernel only roots above
  1e-12, so batched poses can differ from single-call ones by ~1e-7 on rare samples.
* The paper recovers (R, t) with its own SVD-free formula; here the closed form of Horn
  (1990), ``R = cof(E) ∓ [t]x E``, followed by the midpoint-triangulation cheirality test
  (:func:`planarloc.geometry.essential_decomposition.relpose_from_essential_kernel`, equal to
  the SVD route of Hartley & Zisserman 9.6 on exact essential matrices).
* Degeneracy checks the paper does not have, so that degenerate samples give no solution
  rather than spurious ones: rank < 5 of the constraint matrix (smallest ``|R_ii|`` of the
  unit-normalised QR below ``RANK_TOL = 1e-10``: repeated points, all points on one epipolar
  plane), a pure-rotation sample (angles between the five rays preserved to 1e-10: the
  system then has a continuum of solutions), a Gauss-Jordan pivot below 1e-12 of the largest
  entry, ``|p3(z)|`` vanishing at a root.
* Solutions with ``w = 0`` (``E`` in the span of X, Y, Z) are not representable in the
  paper's dehomogenisation either; they are lost (a measure-zero event). Two real roots closer
  than ~1e-5 can turn into a complex pair through the rounding of the polynomial's
  coefficients and are then lost too (Stewénius' solver keeps them); the true solution of a
  non-degenerate sample is a simple root and is not affected.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from planarloc.numerics.sturm import polyval, real_roots_sturm
from planarloc.solvers._five_point import (
    MAX_SOLUTIONS,
    essentials_from_roots,
    five_point_batch,
    five_point_essentials,
    five_point_relposes,
    five_point_sample,
    monomial_permutation,
)
from planarloc.solvers._five_point_calls import FivePointCalls

__all__ = [
    "essentials_5p_nister",
    "relpose_5p_nister",
    "relpose_5p_nister_batch",
    "relpose_5p_nister_batch_unchecked",
]

# Nistér 2004, Sec. 3, monomial order of the 10 x 20 matrix.
_NISTER_ORDER = [
    (3, 0, 0), (0, 3, 0), (2, 1, 0), (1, 2, 0), (2, 0, 1),
    (2, 0, 0), (0, 2, 1), (0, 2, 0), (1, 1, 1), (1, 1, 0),
    (1, 0, 2), (1, 0, 1), (1, 0, 0), (0, 1, 2), (0, 1, 1),
    (0, 1, 0), (0, 0, 3), (0, 0, 2), (0, 0, 1), (0, 0, 0),
]  # fmt: skip
_PERM = monomial_permutation(_NISTER_ORDER)
_FIRST_ROW = 4  # back substitution from ⟨e⟩: rows ⟨a⟩ ... ⟨d⟩ are not used (step 3)


@njit(cache=True)
def _row_polys(A, r_lead, r_low, out):
    """⟨r_lead⟩ − z⟨r_low⟩ as polynomials in z: out[0] (× x), out[1] (× y), out[2] (× 1).

    After elimination row r reads ``lead_r + A[r,10] xz² + A[r,11] xz + A[r,12] x
    + A[r,13] yz² + A[r,14] yz + A[r,15] y + A[r,16] z³ + A[r,17] z² + A[r,18] z + A[r,19]``;
    the leading monomials of the row pairs (e, f), (g, h), (i, j) differ by a factor z and cancel.
    Coefficients ascending in z; out[0], out[1] have degree 3, out[2] degree 4.
    """
    e = A[r_lead]
    f = A[r_low]
    out[0, 0], out[0, 1], out[0, 2], out[0, 3], out[0, 4] = e[12], e[11] - f[12], e[10] - f[11], -f[10], 0.0
    out[1, 0], out[1, 1], out[1, 2], out[1, 3], out[1, 4] = e[15], e[14] - f[15], e[13] - f[14], -f[13], 0.0
    out[2, 0], out[2, 1], out[2, 2] = e[19], e[18] - f[19], e[17] - f[18]
    out[2, 3], out[2, 4] = e[16] - f[17], -f[16]


@njit(cache=True)
def _mul_sub(a, b, c, d, out):
    """out = a * b − c * d for coefficient arrays of length 5 (degree ≤ 4); out has length 9."""
    for k in range(9):
        out[k] = 0.0
    for i in range(5):
        for j in range(5):
            out[i + j] += a[i] * b[j] - c[i] * d[j]


@njit(cache=True)
def nister_roots(A: np.ndarray, sols: np.ndarray) -> int:
    """Steps 4-6 up to ``(x, y, z)``: the real roots of the template ``A`` (10, 20) reduced in
    Nistér's monomial order (back substitution from ⟨e⟩) into ``sols[:n]`` (10, 3); returns n."""
    # rows: a=0 x³, b=1 y³, c=2 x²y, d=3 xy², e=4 x²z, f=5 x², g=6 y²z, h=7 y², i=8 xyz, j=9 xy
    B = np.empty((3, 3, 5))  # B(z): rows ⟨k⟩, ⟨l⟩, ⟨m⟩; columns: coefficients of x, y, 1
    for q in range(3):  # (e, f), (g, h), (i, j)
        _row_polys(A, 4 + 2 * q, 5 + 2 * q, B[q])
    # cofactors of the first row: [x, y, 1] ∝ (p1, p2, p3) = row ⟨l⟩ × row ⟨m⟩
    P = np.empty((3, 9))
    _mul_sub(B[1, 1], B[2, 2], B[1, 2], B[2, 1], P[0])  # p1, degree 7
    _mul_sub(B[1, 2], B[2, 0], B[1, 0], B[2, 2], P[1])  # p2, degree 7
    _mul_sub(B[1, 0], B[2, 1], B[1, 1], B[2, 0], P[2])  # p3, degree 6
    n = np.zeros(11)  # ⟨n⟩ = det B(z), degree 10
    for c in range(3):
        for i in range(5):
            for j in range(min(8, 11 - i)):
                n[i + j] += B[0, c, i] * P[c, j]
    roots = np.empty(10)
    nroots = real_roots_sturm(n, roots)
    p3_scale = 0.0
    for k in range(7):
        p3_scale = max(p3_scale, abs(P[2, k]))
    count = 0
    for s in range(nroots):
        z = roots[s]
        d = polyval(P[2], np.int64(6), z)  # typed degrees, not literals: polyval's one signature
        if abs(d) <= 1e-14 * p3_scale * max(1.0, abs(z)) ** 6:
            continue  # x, y at infinity
        sols[count, 0] = polyval(P[0], np.int64(7), z) / d
        sols[count, 1] = polyval(P[1], np.int64(7), z) / d
        sols[count, 2] = z
        count += 1
    return count


@njit(cache=True)
def nister_essentials(
    xq: np.ndarray, xr: np.ndarray, E_out: np.ndarray, refine_iters: int, refine_rtol: float
) -> int:
    """Kernel: essential matrices from (5, 3) rays; writes E_out[:n] (unit Frobenius norm)."""
    return essentials_from_roots(nister_roots, _PERM, _FIRST_ROW, xq, xr, E_out, refine_iters, refine_rtol)


# ---- the shared five-point drivers bound to this solver's kernel --------------------------------


@njit(cache=True)
def _essentials(xq, xr, E_out):
    return five_point_essentials(nister_essentials, xq, xr, E_out)


@njit(cache=True)
def _relposes(xq, xr, out):
    return five_point_relposes(nister_essentials, xq, xr, out)


@njit(cache=True)
def _batch(xq, xr, R, t, valid):
    five_point_batch(nister_essentials, xq, xr, R, t, valid)


@njit(cache=True, parallel=True)
def _batch_parallel(xq, xr, R, t, valid):
    for m in prange(xq.shape[0]):
        Es = np.empty((MAX_SOLUTIONS, 3, 3))
        five_point_sample(nister_essentials, xq[m], xr[m], Es, R[m], t[m], valid[m])


# ---- the public functions, written once in _five_point_calls ------------------------------------

(
    essentials_5p_nister,
    relpose_5p_nister,
    relpose_5p_nister_batch,
    relpose_5p_nister_batch_unchecked,
) = FivePointCalls(_essentials, _relposes, _batch, _batch_parallel).public_functions(
    __name__,
    "nister",
    solver="Nistér's five-point",
    citation="Nistér 2004",
    references="Nistér, TPAMI 2004, Sec. 3; deviations listed in the module docstring",
)
