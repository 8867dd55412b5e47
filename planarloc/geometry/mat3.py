"""3x3 matrix and 3-vector products for numba kernels, and stores into rows of arrays.

Numba lowers ``A @ B`` on 2-D arrays to a BLAS call, whose fixed cost (~0.3 µs) dwarfs the 27
multiply-adds of a 3x3 product; these scalar versions are what the hot loops use.

Stores write element by element: numba compiles, for every slice assignment of an array
(``out[k] = R``), a shape-mismatch error path per combination of types, 1.2–3.2 s of compile CPU
each (BENCHMARKS.md, "First pose and compile time").
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def store_mat(out: np.ndarray, k: int, M: np.ndarray) -> None:
    """``out[k] = M`` for a (3, 3) ``M`` and ``out`` (N, 3, 3), element by element."""
    for a in range(3):
        for b in range(3):
            out[k, a, b] = M[a, b]


@njit(cache=True, inline="always")
def store_pose(R_out: np.ndarray, t_out: np.ndarray, k: int, R: np.ndarray, t: np.ndarray) -> None:
    """``R_out[k] = R``, ``t_out[k] = t`` for (N, 3, 3) / (N, 3) arrays, element by element."""
    store_mat(R_out, k, R)
    for a in range(3):
        t_out[k, a] = t[a]


@njit(cache=True, inline="always")
def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a · b`` for 3-vectors (numba lowers ``a @ b`` to a BLAS call)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` for 3-vectors."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@njit(cache=True, inline="always")
def mul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for (3, 3) matrices."""
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return C


@njit(cache=True, inline="always")
def mul_into(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> None:
    """``C = A @ B`` for (3, 3) matrices, into C (not A or B): :func:`mul` without its array."""
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True, inline="always")
def mul_t(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B.T`` for (3, 3) matrices (a transposed view costs nothing once inlined)."""
    return mul(A, B.T)


@njit(cache=True, inline="always")
def t_mul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A.T @ B`` for (3, 3) matrices."""
    return mul(A.T, B)


@njit(cache=True, inline="always")
def vec(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A @ v`` for a (3, 3) matrix and a (3,) vector."""
    out = np.empty(3)
    for i in range(3):
        out[i] = A[i, 0] * v[0] + A[i, 1] * v[1] + A[i, 2] * v[2]
    return out


@njit(cache=True, inline="always")
def t_vec(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A.T @ v`` for a (3, 3) matrix and a (3,) vector."""
    return vec(A.T, v)


@njit(cache=True, inline="always")
def sym_eigvals(A: np.ndarray) -> tuple[float, float, float]:
    """Eigenvalues ``λ1 ≥ λ2 ≥ λ3`` of a symmetric (3, 3) matrix, in closed form.

    The trigonometric solution of the characteristic cubic (Smith, CACM 1961): no LAPACK call
    from numba (slow to compile) for a matrix this small.
    """
    p1 = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
    q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    d0, d1, d2 = A[0, 0] - q, A[1, 1] - q, A[2, 2] - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1
    if p2 <= 1e-300:
        return q, q, q
    p = np.sqrt(p2 / 6.0)
    b00, b11, b22 = d0 / p, d1 / p, d2 / p
    b01, b02, b12 = A[0, 1] / p, A[0, 2] / p, A[1, 2] / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = min(1.0, max(-1.0, r))
    phi = np.arccos(r) / 3.0
    e1 = q + 2.0 * p * np.cos(phi)
    e3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return e1, 3.0 * q - e1 - e3, e3
