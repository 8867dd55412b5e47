"""A camera's mount pitch and roll: the rotation that makes it upright, and the angles of a gravity.

The planar solvers assume upright cameras: camera y-axis = gravity (down), so that motion is a
rotation about y plus a translation in x-z (:mod:`planarloc.geometry.planar`). A robot camera
mounted with a fixed pitch/roll is upright after the rotation ``R_upright_from_cam`` about its
centre; the estimators take the mount as a gravity direction per camera
(:class:`planarloc.robust.pair_matches.PairMatches`), so no keypoint is rectified.

Angle conventions (camera frame x right, y down, z forward):

* ``pitch_deg > 0``: the optical axis points below the horizon (camera looking down);
* ``roll_deg > 0``: the camera is turned clockwise about its optical axis as seen from behind
  (its right side lower), so the scene appears turned counter-clockwise in the image.

``R_upright_from_cam = R_x(−pitch) · R_z(roll)`` (pitch about the upright x-axis, then roll
about the camera's own optical axis), with ``R_x(a) = [[1,0,0],[0,c,−s],[0,s,c]]`` and
``R_z(a) = [[c,−s,0],[s,c,0],[0,0,1]]``. The gravity direction seen by the camera is then
``g_cam = (sin r·cos p, cos r·cos p, sin p)``; see :func:`pitch_roll_from_gravity`.

Reference: paper Sec. III-A (upright assumption of local planar motion).
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.validation import InputError, check_array


def _check_angle(name: str, value: float) -> float:
    v = float(value)
    if not np.isfinite(v):
        raise InputError(f"{name}: expected a finite angle in degrees, got {value}")
    return v


def upright_from_cam_rotation(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) rotation ``R_upright_from_cam = R_x(−pitch) · R_z(roll)`` (module conventions).

    Example:
        >>> R = upright_from_cam_rotation(10.0, 0.0)
        >>> bool(R[1, 2] > 0)   # the optical axis has a downward (+y) component
        True
    """
    p = np.radians(_check_angle("pitch_deg", pitch_deg))
    r = np.radians(_check_angle("roll_deg", roll_deg))
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, sp], [0.0, -sp, cp]])  # R_x(-pitch)
    Rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return Rx @ Rz


def pitch_roll_from_gravity(gravity_cam: object) -> tuple[float, float]:
    """Pitch and roll in degrees from the gravity direction in camera coordinates.

    Args:
        gravity_cam: (3,) direction of gravity (down) in the camera frame, any length > 0,
            e.g. from an IMU or from a ground-truth pose: ``cam_from_world.R @ g_world``.

    Returns:
        ``(pitch_deg, roll_deg)`` with ``upright_from_cam_rotation(pitch, roll) @ g_cam ∝ (0, 1, 0)``.

    Raises:
        InputError: on a zero vector.

    The decomposition keeps ``|pitch| <= 90°``; a camera mounted upside down gets ``|roll| > 90°``.
    """
    g = check_array("gravity_cam", gravity_cam, (3,))
    n = np.linalg.norm(g)
    if n == 0:
        raise InputError("gravity_cam: zero vector; hint: pass the direction of gravity in camera axes")
    g = g / n
    pitch = np.degrees(np.arcsin(np.clip(g[2], -1.0, 1.0)))
    roll = np.degrees(np.arctan2(g[0], g[1]))
    return float(pitch), float(roll)
