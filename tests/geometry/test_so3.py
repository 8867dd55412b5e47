"""SO(3) maps (planarloc.geometry.so3): round trips, the kernel against the stacked map, and the
left Jacobian's inverse against a finite difference."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.so3 import exp_so3, so3_exp, so3_left_jacobian_inverse, so3_log


def _vectors(rng: np.random.Generator) -> np.ndarray:
    w = rng.normal(size=(50, 3))
    w *= rng.uniform(0, np.pi - 1e-2, (50, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    return np.vstack([w, [[0, 0, 0], [1e-10, 0, 0], [0, 1e-7, 0], [0, 0, np.pi - 1e-4]]])


def test_exp_is_rodrigues_and_log_inverts_it() -> None:
    w = _vectors(np.random.default_rng(0))
    R = so3_exp(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(so3_log(R), w, atol=1e-9)
    np.testing.assert_allclose(
        R @ np.transpose(R, (0, 2, 1)), np.broadcast_to(np.eye(3), R.shape), atol=1e-14
    )


def test_the_kernel_is_the_stacked_map_of_one_vector() -> None:
    for w in _vectors(np.random.default_rng(1)):
        np.testing.assert_allclose(exp_so3(np.ascontiguousarray(w)), so3_exp(w)[0], rtol=0, atol=2e-15)


def test_left_jacobian_inverse_linearises_the_log() -> None:
    rng = np.random.default_rng(2)
    phi = _vectors(rng)[:50]
    eps = 1e-7 * rng.normal(size=(50, 3))
    moved = so3_log(so3_exp(eps) @ so3_exp(phi))
    predicted = phi + np.einsum("nij,nj->ni", so3_left_jacobian_inverse(phi), eps)
    np.testing.assert_allclose(moved, predicted, atol=1e-12)


def test_pose_graph_uses_these_maps() -> None:
    from planarloc.robust import pose_graph, refinement

    assert pose_graph.so3_exp is so3_exp and pose_graph.so3_log is so3_log
    assert refinement.exp_so3 is exp_so3
