"""Real eigenvalues of small nonsymmetric matrices (planarloc.numerics.eigen)."""

from __future__ import annotations

import numpy as np

from planarloc.numerics.eigen import real_eigenvalues


def test_real_eigenvalues_match_numpy():
    rng = np.random.default_rng(18)
    out = np.empty(10)
    for _ in range(100):
        M = rng.normal(size=(10, 10)) * rng.uniform(0.1, 100)
        ref = np.linalg.eigvals(M)
        ref = np.sort(ref.real[np.abs(ref.imag) <= 1e-10 * np.maximum(1, np.abs(ref.real))])
        count = real_eigenvalues(M, out)
        assert count == len(ref)
        assert np.allclose(np.sort(out[:count]), ref, rtol=1e-9, atol=1e-9)


def test_real_eigenvalues_of_triangular_and_rotation_blocks():
    out = np.empty(4)
    T = np.triu(np.arange(1.0, 17.0).reshape(4, 4))  # eigenvalues on the diagonal: 1, 6, 11, 16
    assert real_eigenvalues(T, out) == 4 and np.allclose(np.sort(out), [1.0, 6.0, 11.0, 16.0])
    R = np.zeros((4, 4))
    R[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # ±i: not real
    R[2:, 2:] = np.diag([2.0, -3.0])
    assert real_eigenvalues(R, out) == 2 and np.allclose(np.sort(out[:2]), [-3.0, 2.0])
