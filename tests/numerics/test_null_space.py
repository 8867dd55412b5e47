"""Householder null-space basis: orthonormal, annihilated by the matrix, the span of SciPy's
SVD null space, and a refusal of rank-deficient input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

from planarloc.numerics.null_space import null_space_qr


@pytest.mark.parametrize("rows", [5, 8])
def test_basis_is_orthonormal_and_spans_the_null_space(rows: int) -> None:
    rng = np.random.default_rng(rows)
    for _ in range(20):
        A = rng.normal(size=(rows, 9))
        basis = np.empty((9, 9 - rows))
        assert null_space_qr(np.ascontiguousarray(A.T), basis, 1e-10)
        np.testing.assert_allclose(basis.T @ basis, np.eye(9 - rows), atol=1e-12)
        np.testing.assert_allclose(A @ basis, 0.0, atol=1e-12)
        ref = null_space(A)  # same subspace: the projectors agree
        np.testing.assert_allclose(basis @ basis.T, ref @ ref.T, atol=1e-12)


def test_rank_deficient_matrix_gives_no_basis() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 9))
    A[4] = 2.0 * A[1] - A[3]  # rank 4
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    assert not null_space_qr(np.ascontiguousarray(A.T), np.empty((9, 4)), 1e-10)
