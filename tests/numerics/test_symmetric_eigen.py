"""The cyclic Jacobi eigen-decomposition against LAPACK (numpy.linalg.eigh)."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.numerics.symmetric_eigen import symmetric_eigen


def _decompose(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = len(A)
    w, V = np.empty(n), np.empty((n, n))
    assert symmetric_eigen(np.ascontiguousarray(A), w, V)
    return w, V


@pytest.mark.parametrize("n", [1, 2, 3, 6, 9])
def test_matches_eigh_on_random_symmetric_matrices(n: int) -> None:
    rng = np.random.default_rng(n)
    for k in range(50):
        B = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-5, 5, size=n)  # badly scaled columns
        A = B @ B.T if k % 2 else B + B.T  # SPD, then indefinite
        w, V = _decompose(A)
        scale = np.abs(A).max()
        assert np.all(np.diff(w) >= 0)  # ascending, like eigh
        np.testing.assert_allclose(w, np.linalg.eigvalsh(A), rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(n), atol=1e-12)
        np.testing.assert_allclose(V @ np.diag(w) @ V.T, A, rtol=0, atol=1e-12 * scale)


def test_repeated_eigenvalues_and_diagonal_input() -> None:
    w, V = _decompose(np.diag([3.0, 1.0, 3.0, 2.0]))
    np.testing.assert_array_equal(w, [1.0, 2.0, 3.0, 3.0])
    np.testing.assert_array_equal(np.abs(V[:, 0]), [0, 1, 0, 0])
    Q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(6, 6)))
    A = Q @ np.diag([1e-9, 1e-9, 1.0, 1.0, 1.0, 5.0]) @ Q.T  # two nearly null directions
    w, V = _decompose(A)
    np.testing.assert_allclose(w, [1e-9, 1e-9, 1, 1, 1, 5], atol=1e-12)
    null = Q[:, :2]  # the smallest two span them
    np.testing.assert_allclose(np.linalg.norm(null.T @ V[:, :2], axis=0), 1.0, atol=1e-9)


def test_non_finite_input_is_refused() -> None:
    A = np.eye(3)
    A[0, 2] = A[2, 0] = np.nan
    assert not symmetric_eigen(A, np.empty(3), np.empty((3, 3)))
    A[0, 2] = A[2, 0] = np.inf
    assert not symmetric_eigen(A, np.empty(3), np.empty((3, 3)))
