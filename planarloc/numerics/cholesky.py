"""Cholesky factorisation and solves of small symmetric positive-definite matrices (numba).

Hand-written: numba's ``np.linalg.solve`` / ``cholesky`` pull in LAPACK bindings that take tens
of seconds to compile, for the 6x6 to 9x9 systems of the refinements and verification kernels,
which these solve in ~100 ns.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["cholesky_factor", "cholesky_solve", "solve_spd", "spd_inverse"]


@njit(cache=True, error_model="numpy")
def cholesky_factor(A: np.ndarray, L: np.ndarray, rel_tol: float) -> bool:
    """Lower Cholesky factor of a small SPD matrix into L; False when a pivot falls below
    ``rel_tol`` times the largest diagonal entry (singular relative to its scale)."""
    n = A.shape[0]
    scale = 0.0
    for i in range(n):
        scale = max(scale, A[i, i])
    if not scale > 0.0:
        return False
    L[:] = 0.0
    for i in range(n):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > rel_tol * scale:
                    return False
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    return True


@njit(cache=True, error_model="numpy")
def cholesky_solve(L: np.ndarray, b: np.ndarray, x: np.ndarray) -> None:
    """Solve ``L Lᵀ x = b`` (x (n,)) by forward and back substitution with the factor of
    :func:`cholesky_factor`."""
    n = L.shape[0]
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


@njit(cache=True, error_model="numpy")
def solve_spd(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> bool:
    """Solve ``A x = b`` for a small symmetric positive-definite A by Cholesky; False if not SPD.

    Hand-written: numba's ``np.linalg.solve`` pulls in LAPACK bindings that take tens of
    seconds to compile, for a 6x6 system that this solves in ~100 ns.
    """
    L = np.empty(A.shape)
    if not cholesky_factor(A, L, 0.0):
        return False
    cholesky_solve(L, b, x)
    return True


@njit(cache=True, error_model="numpy")
def spd_inverse(A: np.ndarray, out: np.ndarray, rel_tol: float = 0.0) -> bool:
    """Inverse of a small symmetric positive-definite A into ``out`` (n, n) by one Cholesky
    factorisation and n solves; False (``out`` undefined) if A is not SPD, or singular relative
    to its scale: a pivot below ``rel_tol`` times its largest diagonal entry
    (:func:`cholesky_factor`)."""
    n = A.shape[0]
    L = np.empty((n, n))
    if not cholesky_factor(A, L, rel_tol):
        return False
    e = np.zeros(n)
    col = np.empty(n)
    for b in range(n):
        e[:] = 0.0
        e[b] = 1.0
        cholesky_solve(L, e, col)
        for a in range(n):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            out[a, b] = col[a]
    return True
