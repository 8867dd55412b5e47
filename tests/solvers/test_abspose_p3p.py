"""Perspective-three-point (6DoF absolute pose from 2D-3D), cross-checked against PoseLib."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.validation import InputError
from planarloc.solvers import abspose_p3p


def p3p_case(
    rng: np.random.Generator, unit_rays: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    t = rng.uniform(-3, 3, 3)
    Xc = rng.uniform([-3, -3, 1], [3, 3, 12], (3, 3))
    x = Xc / np.linalg.norm(Xc, axis=1, keepdims=True) if unit_rays else Xc / Xc[:, 2:]
    return R, t, (Xc - t) @ R, x


@pytest.mark.parametrize("unit_rays", [False, True])
def test_exact_recovery_and_cheirality(unit_rays: bool) -> None:
    rng = np.random.default_rng(1 + unit_rays)
    for _ in range(300):
        R, t, X, x = p3p_case(rng, unit_rays)
        sols = abspose_p3p(x, X)
        assert 1 <= len(sols) <= 4
        assert min(np.abs(p.R - R).max() + np.abs(p.t - t).max() for p in sols) < 1e-7
        for p in sols:  # every solution is a rotation, fits the rays and puts the points in front
            assert np.allclose(p.R @ p.R.T, np.eye(3), atol=1e-9) and np.linalg.det(p.R) > 0
            Xc = X @ p.R.T + p.t
            assert np.all(Xc[:, 2] > 0)
            cos = np.einsum(
                "ij,ij->i",
                Xc / np.linalg.norm(Xc, axis=1, keepdims=True),
                x / np.linalg.norm(x, axis=1, keepdims=True),
            )
            assert np.all(cos > 1 - 1e-9)


def test_same_solutions_as_poselib() -> None:
    poselib = pytest.importorskip("poselib")
    rng = np.random.default_rng(7)
    for _ in range(100):
        _, _, X, x = p3p_case(rng)
        ours = abspose_p3p(x, X)
        theirs = poselib.p3p(list(x / np.linalg.norm(x, axis=1, keepdims=True)), list(X))
        assert len(ours) == len(theirs)
        for q in theirs:
            assert min(np.abs(p.R - q.R).max() + np.abs(p.t - q.t).max() for p in ours) < 1e-6


def test_degenerate_and_bad_input() -> None:
    rng = np.random.default_rng(3)
    _, _, X, x = p3p_case(rng)
    collinear = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 6.0], [2.0, 0.0, 7.0]])
    assert abspose_p3p(collinear / collinear[:, 2:], collinear) == []
    assert abspose_p3p(x, np.stack([X[0], X[0], X[1]])) == []  # coincident points
    with pytest.raises(InputError, match="x_query"):
        abspose_p3p(x[:2], X[:2])
    with pytest.raises(InputError):
        abspose_p3p(np.full((3, 3), np.nan), X)
    with pytest.raises(InputError, match="all zero"):
        abspose_p3p(np.zeros((3, 3)), X)
