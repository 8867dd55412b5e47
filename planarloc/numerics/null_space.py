"""Orthonormal basis of the null space of a small wide matrix, by Householder QR of its transpose.

For an ``(r, m)`` matrix ``A`` of full row rank ``r < m``, the Householder QR ``Aᵀ = Q R`` gives
``Q``'s last ``m − r`` columns as an orthonormal basis of ``null(A)``. This is step 1 of the
five-point solvers (Nistér 2004, Sec. 3: "QR or SVD", a 5 × 9 system) and the linear step of the
minimal 8-point solver (an 8 × 9 system): a fixed number of scalar loops, no LAPACK call (which
from numba costs more than the whole solver).

References:
    G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., Sec. 5.2.1-5.2.2 (Householder
    QR; ``Q`` applied to unit vectors in backward order, Sec. 5.1.6).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["null_space_qr"]


@njit(cache=True, inline="always")
def null_space_qr(At: np.ndarray, basis: np.ndarray, rank_tol: float) -> bool:
    """Orthonormal basis of the null space of ``A`` from the Householder QR of ``At = Aᵀ``.

    Inlined into the calling kernel (``inline="always"``): there the loop bounds are the
    constant shape of its ``At`` and the floating-point flags are the caller's, so the compiled
    loops are those of a solver-specific version.

    Args:
        At: (m, r) transpose of the matrix, ``r < m``; overwritten (it holds ``R`` afterwards).
            Its columns should have comparable norms (e.g. unit) for ``rank_tol`` to mean
            something.
        basis: (m, m − r) output: column ``c`` is ``Q e_{r+c}``, orthonormal and orthogonal to
            every column of ``At``.
        rank_tol: ``A`` counts as rank deficient if the norm of a Householder column (the
            ``|R_kk|`` to be) falls below this.

    Returns:
        False for a rank-deficient matrix (``basis`` is then undefined).
    """
    m, r = At.shape
    V = np.zeros((m, r))
    beta = np.zeros(r)
    for k in range(r):
        norm = 0.0
        for i in range(k, m):
            norm += At[i, k] * At[i, k]
        norm = np.sqrt(norm)
        if norm < rank_tol:
            return False
        alpha = -norm if At[k, k] >= 0.0 else norm
        for i in range(k, m):
            V[i, k] = At[i, k]
        V[k, k] -= alpha
        vnorm2 = 0.0
        for i in range(k, m):
            vnorm2 += V[i, k] * V[i, k]
        beta[k] = 2.0 / vnorm2
        At[k, k] = alpha
        for j in range(k + 1, r):
            s = 0.0
            for i in range(k, m):
                s += V[i, k] * At[i, j]
            s *= beta[k]
            for i in range(k, m):
                At[i, j] -= s * V[i, k]
    q = np.empty(m)
    for c in range(m - r):
        for i in range(m):
            q[i] = 0.0
        q[r + c] = 1.0
        for k in range(r - 1, -1, -1):
            s = 0.0
            for i in range(k, m):
                s += V[i, k] * q[i]
            s *= beta[k]
            for i in range(k, m):
                q[i] -= s * V[i, k]
        for i in range(m):
            basis[i, c] = q[i]
    return True
