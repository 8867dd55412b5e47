"""The local planar motion model of the paper (Sec. III-A, eq. 1-2).

Upright convention: the camera y-axis is the gravity direction (pointing down), so planar
motion between two upright cameras is a rotation about y plus a translation in x-z.

The paper parametrises the relative pose ``ref_from_query`` (``x_ref = R x_query + t``) by
the yaw ``θ``, the translation direction ``φ`` and the scale ``ρ`` (eq. 1)::

    R = [[cos θ, 0, -sin θ],        t = -R ρ [sin φ, 0, cos φ]ᵀ
         [0,     1,  0    ],
         [sin θ, 0,  cos θ]]

so ``ρ [sin φ, 0, cos φ]`` is the reference camera centre seen from the query camera, and
the essential matrix ``E = [t]x R`` becomes (eq. 2)::

    E = ρ [[0, cos(θ-φ), 0], [-cos φ, 0, sin φ], [0, sin(θ-φ), 0]]
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array


def rotation_from_yaw(theta: float | np.ndarray) -> np.ndarray:
    """Paper eq. (1) rotation about the y-axis.

    Args:
        theta: yaw in radians, scalar or (...,) array.

    Returns:
        (..., 3, 3) rotation matrices ``[[c, 0, -s], [0, 1, 0], [s, 0, c]]``.
    """
    theta = np.asarray(theta, dtype=float)
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(theta.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 2] = -s
    R[..., 1, 1] = 1.0
    R[..., 2, 0] = s
    R[..., 2, 2] = c
    return R


def yaw_from_rotation(R: np.ndarray) -> float:
    """Inverse of :func:`rotation_from_yaw` for an upright rotation: ``atan2(R[2,0], R[0,0])``."""
    return float(np.arctan2(R[2, 0], R[0, 0]))


def relpose_from_planar_params(theta: float, phi: float, rho: float = 1.0) -> Pose:
    """``ref_from_query`` from the paper's (θ, φ, ρ), eq. (1)."""
    R = rotation_from_yaw(theta)
    t = -R @ (rho * np.array([np.sin(phi), 0.0, np.cos(phi)]))
    return Pose(R, t)


def planar_params_from_relpose(ref_from_query: Pose, tol: float = 1e-6) -> tuple[float, float, float]:
    """(θ, φ, ρ) of an upright relative pose; inverse of :func:`relpose_from_planar_params`.

    Raises:
        InputError: if the pose is not planar within ``tol`` (rotation not about y, or
            translation with a y component).
    """
    if not is_planar(ref_from_query, tol):
        raise InputError(
            "ref_from_query is not a planar motion (rotation about y and translation in x-z); "
            "hint: check that both cameras are upright (y = gravity)"
        )
    theta = yaw_from_rotation(ref_from_query.R)
    c = ref_from_query.center  # query-frame position of the reference centre: ρ (sin φ, 0, cos φ)
    rho = float(np.hypot(c[0], c[2]))
    phi = float(np.arctan2(c[0], c[2])) if rho > 0 else 0.0
    return theta, phi, rho


def essential_from_planar_params(theta: float, phi: float, rho: float = 1.0) -> np.ndarray:
    """(3, 3) essential matrix of eq. (2) with ``x_refᵀ E x_query = 0``."""
    return rho * np.array(
        [
            [0.0, np.cos(theta - phi), 0.0],
            [-np.cos(phi), 0.0, np.sin(phi)],
            [0.0, np.sin(theta - phi), 0.0],
        ]
    )


def is_planar(b_from_a: Pose, tol: float = 1e-6) -> bool:
    """True if ``b_from_a`` is a rotation about y and a translation in the x-z plane."""
    R, t = b_from_a.R, b_from_a.t
    scale = max(1.0, float(np.linalg.norm(t)))
    return bool(
        abs(R[1, 1] - 1.0) < tol
        and np.abs(R[1, [0, 2]]).max() < tol
        and np.abs(R[[0, 2], 1]).max() < tol
        and abs(t[1]) < tol * scale
    )


def upright_tilt_deg(cam_from_world: Pose, gravity_world: object = (0.0, 1.0, 0.0)) -> float:
    """Angle in degrees between the camera y-axis and the world gravity direction."""
    g = check_array("gravity_world", gravity_world, (3,))
    g = g / np.linalg.norm(g)
    y_cam_in_world = cam_from_world.R[1]  # row 1 of R = camera y-axis in world coordinates
    return float(np.degrees(np.arccos(np.clip(y_cam_in_world @ g, -1.0, 1.0))))
