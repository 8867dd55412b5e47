"""Gravity-levelled ("upright") frames of tilted cameras.

The planar model (:mod:`planarloc.geometry.planar`) holds between *upright* frames: camera
y-axis = gravity (pointing down). A camera whose gravity direction in its own frame is
``g`` (unit, pointing down; an IMU's reading, or ``R_cam_from_world · g_world``) is made
upright by a pure rotation ``U = upright_from_cam`` with ``U g = (0, 1, 0)``. Of all such
rotations we take the smallest one (rotation about ``g × e_y``), so an upright camera gets
``U = I`` and the yaw of the optical axis is kept. Bearings ``x`` become ``U x``; a pose
``upright_from_world`` solved from them is mapped back by ``cam_from_world = Uᵀ ·
upright_from_world``. See docs/conventions.md, "Gravity".
"""

from __future__ import annotations

import numpy as np

E_Y = np.array([0.0, 1.0, 0.0])


def upright_from_gravity(gravity_cam: np.ndarray) -> np.ndarray:
    """(..., 3, 3) smallest rotations ``U`` with ``U g = e_y`` for (..., 3) gravity directions.

    Args:
        gravity_cam: (..., 3) gravity (down) in the camera frame; any positive length.

    Returns:
        (..., 3, 3) ``upright_from_cam`` rotations (Rodrigues about ``g × e_y``); identity
        for ``g ∥ e_y``. ``g = -e_y`` (camera upside down) gives the rotation by π about x.

    Example:
        >>> U = upright_from_gravity(np.array([0.0, np.cos(0.1), np.sin(0.1)]))
        >>> bool(np.allclose(U @ [0.0, np.cos(0.1), np.sin(0.1)], [0, 1, 0]))
        True
    """
    g = np.asarray(gravity_cam, dtype=float)
    g = g / np.linalg.norm(g, axis=-1, keepdims=True)
    axis = np.cross(g, E_Y)  # sin(angle) · unit axis
    s = np.linalg.norm(axis, axis=-1)[..., None, None]
    c = g[..., 1][..., None, None]  # cos(angle) = g · e_y
    K = np.zeros(g.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -axis[..., 2], axis[..., 1]
    K[..., 1, 0], K[..., 1, 2] = axis[..., 2], -axis[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -axis[..., 1], axis[..., 0]
    eye = np.broadcast_to(np.eye(3), K.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        U = eye + K + (K @ K) / (1.0 + c)  # Rodrigues with (1 - cos)/sin² = 1/(1 + cos)
    flip = (c[..., 0, 0] < -1.0 + 1e-12) & (s[..., 0, 0] < 1e-9)
    if np.any(flip):
        U[flip] = np.diag([1.0, -1.0, -1.0])
    return U


def tilt_between_deg(gravity_a: np.ndarray, gravity_b: np.ndarray) -> np.ndarray:
    """(...,) angle in degrees between two (..., 3) gravity directions."""
    a = np.asarray(gravity_a, dtype=float)
    b = np.asarray(gravity_b, dtype=float)
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mean_direction(directions: np.ndarray) -> np.ndarray:
    """(3,) normalised mean of (N, 3) unit directions (the chordal L2 mean)."""
    d = np.asarray(directions, dtype=float)
    m = (d / np.linalg.norm(d, axis=1, keepdims=True)).mean(axis=0)
    return m / np.linalg.norm(m)
