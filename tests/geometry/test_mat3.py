"""The scalar 3x3 products of planarloc.geometry.mat3 equal numpy's, inside a compiled kernel,
for contiguous matrices and for strided views."""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3


@njit
def _products(A, B, v):
    return (
        mat3.mul(A, B),
        mat3.mul_t(A, B),
        mat3.t_mul(A, B),
        mat3.vec(A, v),
        mat3.t_vec(A, v),
        mat3.dot(v, B[0]),
        mat3.cross(v, B[1]),
    )


def test_products_match_numpy_for_contiguous_and_strided_matrices() -> None:
    rng = np.random.default_rng(0)
    big = rng.normal(size=(2, 6, 6))
    v = rng.normal(size=3)
    for A, B in ((big[0, :3, :3].copy(), big[1, :3, :3].copy()), (big[0, ::2, ::2], big[1, 1::2, ::2])):
        mul, mul_t, t_mul, vec, t_vec, dot, cross = _products(A, B, v)
        np.testing.assert_allclose(mul, A @ B, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(mul_t, A @ B.T, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(t_mul, A.T @ B, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(vec, A @ v, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(t_vec, A.T @ v, rtol=1e-14, atol=1e-14)
        assert abs(dot - float(v @ B[0])) < 1e-14
        np.testing.assert_allclose(cross, np.cross(v, B[1]), rtol=1e-14, atol=1e-14)
