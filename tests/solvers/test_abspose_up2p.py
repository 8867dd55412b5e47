"""Upright 2-point absolute pose from 2D-3D correspondences (structure mode)."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.validation import InputError
from planarloc.solvers import abspose_up2p


def upright_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    R = rotation_from_yaw(rng.uniform(-np.pi, np.pi))
    t = rng.uniform(-3, 3, 3)
    while True:
        X = rng.uniform(-5, 5, (2, 3))
        Xc = X @ R.T + t
        if np.all(Xc[:, 2] > 0.5):
            return R, t, X, Xc / Xc[:, 2:]


@pytest.mark.parametrize("seed", range(5))
def test_exact_recovery_and_cheirality(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(50):
        R, t, X, x = upright_case(rng)
        sols = abspose_up2p(x, X)
        assert 1 <= len(sols) <= 2
        assert min(np.abs(p.R - R).max() + np.abs(p.t - t).max() for p in sols) < 1e-8
        for p in sols:  # every solution is upright and puts both points in front
            assert abs(p.R[1, 1] - 1.0) < 1e-12 and np.all((X @ p.R.T + p.t)[:, 2] > 0)


def test_degenerate_and_bad_input() -> None:
    rng = np.random.default_rng(9)
    _, _, X, x = upright_case(rng)
    assert abspose_up2p(np.stack([x[0], x[0]]), np.stack([X[0], X[0]])) == []
    with pytest.raises(InputError):
        abspose_up2p(x[:1], X[:1])
    with pytest.raises(InputError):
        abspose_up2p(np.full((2, 3), np.nan), X)
