"""Eigen-decomposition of a small dense symmetric matrix (cyclic Jacobi), for compiled kernels.

Hand-written: numba's ``np.linalg.eigh`` pulls in LAPACK bindings that take seconds to compile,
and from Python ``np.linalg.eigh`` costs ~40 µs per 6 × 6 matrix (dispatch and error-state
handling), where this takes about a microsecond inside a kernel.

Reference: G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., Sec. 8.5 (the cyclic
Jacobi method; rotations as in Numerical Recipes, 3rd ed., Sec. 11.1, ``jacobi``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["symmetric_eigen"]

MAX_SWEEPS = 50  # quadratic convergence: a 6 x 6 matrix needs 5-8 sweeps


@njit(cache=True, error_model="numpy")
def symmetric_eigen(A: np.ndarray, w: np.ndarray, V: np.ndarray) -> bool:
    """Eigenvalues ``w`` (n,) in ascending order and unit eigenvectors ``V[:, k]`` (n, n) of the
    symmetric A (n, n) (only its upper triangle is read), like ``np.linalg.eigh``; False if A has
    a non-finite entry or the sweeps did not converge (``w``, ``V`` undefined then)."""
    n = A.shape[0]
    a = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            if not np.isfinite(A[i, j]):
                return False
            a[i, j] = a[j, i] = A[i, j]
    V[:, :] = 0.0
    for i in range(n):
        V[i, i] = 1.0
    converged = False
    for _ in range(MAX_SWEEPS):
        off, scale = 0.0, 0.0
        for i in range(n):
            scale += a[i, i] * a[i, i]
            for j in range(i + 1, n):
                off += a[i, j] * a[i, j]
        if off <= 1e-30 * scale or off == 0.0:
            converged = True
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                if a[p, q] == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                tt = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    tt = -tt
                c = 1.0 / np.sqrt(tt * tt + 1.0)
                s = tt * c
                for k in range(n):  # a <- a J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):  # a <- Jᵀ a (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                a[p, q] = a[q, p] = 0.0
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    if not converged:
        return False
    for i in range(n):  # insertion sort of the eigenpairs by eigenvalue
        w[i] = a[i, i]
    for i in range(1, n):
        j = i
        while j > 0 and w[j - 1] > w[j]:
            w[j - 1], w[j] = w[j], w[j - 1]
            for k in range(n):
                V[k, j - 1], V[k, j] = V[k, j], V[k, j - 1]
            j -= 1
    return True
