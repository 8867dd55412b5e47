"""The rotation group SO(3): exponential and logarithm maps and the left Jacobian's inverse.

A rotation vector ``ω`` (radians, axis × angle) maps to ``R = exp([ω]×)`` by Rodrigues' formula;
``log`` is its inverse with ``‖ω‖ ≤ π``. :func:`so3_exp`, :func:`so3_log` and
:func:`so3_left_jacobian_inverse` work on stacks of N in numpy; :func:`exp_so3` is the same map
for one vector as a numba kernel, called from the refinement kernels.

References:
    Barfoot, "State Estimation for Robotics", 2017, eq. (7.77) (left Jacobian of SO(3)).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from planarloc.geometry import mat3 as m3
from planarloc.geometry.epipolar import skew


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors (radians) -> (N, 3, 3) rotation matrices (Rodrigues)."""
    w = np.asarray(omega, dtype=float).reshape(-1, 3)
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(ths) / ths)
    b = np.where(small, 0.5, (1.0 - np.cos(ths)) / ths**2)
    K = skew(w)
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 3) rotation vectors (radians, norm ≤ π)."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(cos)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    small = th < 1e-6
    f = np.where(small, 0.5 + th**2 / 12.0, th / (2.0 * np.sin(np.where(small, 1.0, th))))
    out = f[:, None] * v
    near_pi = th > np.pi - 1e-3  # sin θ → 0: the antisymmetric part loses the axis
    if near_pi.any():
        out[near_pi] = Rotation.from_matrix(R[near_pi]).as_rotvec()
    return out


def so3_left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) ``J_l⁻¹(φ)``: ``log(exp(ε) exp(φ)) ≈ φ + J_l⁻¹(φ) ε`` (Barfoot eq. 7.77)."""
    phi = np.asarray(phi, dtype=float).reshape(-1, 3)
    th = np.linalg.norm(phi, axis=1)
    P = skew(phi)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    coef = np.where(small, 1.0 / 12.0, 1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    return np.eye(3)[None] - 0.5 * P + coef[:, None, None] * (P @ P)


@njit(cache=True, error_model="numpy")
def exp_so3(w: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (radians) -> (3, 3) rotation matrix: :func:`so3_exp` of one vector,
    as a kernel (first order below 1e-12 rad)."""
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / (th * th) * m3.mul(K, K)


@njit(cache=True, error_model="numpy")
def exp_so3_into(w: np.ndarray, out: np.ndarray) -> None:
    """:func:`exp_so3` of ``w[:3]`` written into ``out`` (3, 3), with the same arithmetic but
    none of its five temporary arrays: the refinements' inner loops call it once per step tried."""
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = ((0.0, -w[2], w[1]), (w[2], 0.0, -w[0]), (-w[1], w[0], 0.0))
    a, b = 1.0, 0.0
    if not th < 1e-12:
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / (th * th)
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            if th < 1e-12:
                out[i, j] = eye + K[i][j]
            else:
                KK = K[i][0] * K[0][j] + K[i][1] * K[1][j] + K[i][2] * K[2][j]
                out[i, j] = eye + a * K[i][j] + b * KK
