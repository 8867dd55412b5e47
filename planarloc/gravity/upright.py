"""Upright rectification of a camera mounted with a known pitch and roll.

The planar solvers assume upright cameras: camera y-axis = gravity (down), so that motion is a
rotation about y plus a translation in x-z (:mod:`planarloc.geometry.planar`). A robot camera
mounted with a fixed pitch/roll is made upright by a pure rotation about its centre, i.e. by
the homography ``H = K_v · R_upright_from_cam · K⁻¹`` to a *virtual* upright camera
``K_v`` (default: the same pinhole intrinsics, no distortion). Keypoints are rectified, not
images: features are detected on the original image and mapped afterwards.

Angle conventions (camera frame x right, y down, z forward):

* ``pitch_deg > 0``: the optical axis points below the horizon (camera looking down);
* ``roll_deg > 0``: the camera is turned clockwise about its optical axis as seen from behind
  (its right side lower), so the scene appears turned counter-clockwise in the image.

``R_upright_from_cam = R_x(−pitch) · R_z(roll)`` (pitch about the upright x-axis, then roll
about the camera's own optical axis), with ``R_x(a) = [[1,0,0],[0,c,−s],[0,s,c]]`` and
``R_z(a) = [[c,−s,0],[s,c,0],[0,0,1]]``. The gravity direction seen by the camera is then
``g_cam = (sin r·cos p, cos r·cos p, sin p)``; see :func:`pitch_roll_from_gravity`.

References:
    Hartley & Zisserman, "Multiple View Geometry", 2nd ed., Sec. 8.4 (homography of a pure
    rotation, ``H = K R K⁻¹``). Paper Sec. III-A (upright assumption of local planar motion).
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.camera import Camera, CameraModel
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


def rectify_homography(
    camera: Camera, pitch_deg: float, roll_deg: float, K_virtual: object | None = None
) -> np.ndarray:
    """Homography from (undistorted) pixels of ``camera`` to pixels of the upright virtual camera.

    Args:
        camera: the real camera; only its pinhole part ``K`` is used (for an ``OPENCV``
            camera, distorted keypoints must go through :func:`rectify_keypoints`).
        pitch_deg, roll_deg: mounting angles of the real camera (module conventions).
        K_virtual: (3, 3) intrinsics of the virtual camera; default ``camera.K``.

    Returns:
        (3, 3) ``H = K_v R_upright_from_cam K⁻¹``, acting on homogeneous pixels
        ``(u, v, 1)``; normalised so ``H[2, 2] = 1`` when possible.

    References:
        Hartley & Zisserman, MVG 2nd ed., Sec. 8.4 (camera rotation).
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    Kv = camera.K if K_virtual is None else check_array("K_virtual", K_virtual, (3, 3))
    H = Kv @ upright_from_cam_rotation(pitch_deg, roll_deg) @ np.linalg.inv(camera.K)
    if abs(H[2, 2]) > 1e-12:
        H = H / H[2, 2]
    return H


def apply_homography(H: object, points: object) -> tuple[np.ndarray, np.ndarray]:
    """Map (N, 2) pixels through a (3, 3) homography.

    Returns:
        ``(mapped (N, 2), in_front (N,) bool)``; ``in_front`` is False where the homogeneous
        scale is <= 0 (the ray points behind the target camera; those rows are still the
        algebraic projection and must not be used).
    """
    H = check_array("H", H, (3, 3))
    pts = check_array("points", points, (None, 2))
    xh = pts @ H[:, :2].T + H[:, 2]
    w = xh[:, 2]
    in_front = w > 0
    safe = np.where(np.abs(w) < 1e-300, 1e-300, w)
    return xh[:, :2] / safe[:, None], in_front


def rectify_keypoints(
    camera: Camera, keypoints: object, pitch_deg: float, roll_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of the real (possibly distorted) camera -> pixels of the upright virtual camera.

    The virtual camera is :func:`rectified_camera` (``camera.K``, no distortion).

    Args:
        camera: real camera (distortion is removed first).
        keypoints: (N, 2) pixels of the real image (OpenCV convention).
        pitch_deg, roll_deg: mounting angles (module conventions).

    Returns:
        ``(points (N, 2), in_front (N,) bool)``, see :func:`apply_homography`.
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    rays = upright_bearings(camera, keypoints, pitch_deg, roll_deg)
    return _project(camera, rays)


def _project(camera: Camera, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    in_front = rays[:, 2] > 0
    z = np.where(np.abs(rays[:, 2]) < 1e-300, 1e-300, rays[:, 2])
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    return np.stack([fx * rays[:, 0] / z + cx, fy * rays[:, 1] / z + cy], axis=1), in_front


def unrectify_keypoints(
    camera: Camera, points: object, pitch_deg: float, roll_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`rectify_keypoints`: virtual upright pixels -> real (distorted) pixels.

    Returns:
        ``(keypoints (N, 2), in_front (N,) bool)``; ``in_front`` False where the ray is behind
        the real camera.
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    pts = check_array("points", points, (None, 2))
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    rays_u = np.stack([(pts[:, 0] - cx) / fx, (pts[:, 1] - cy) / fy, np.ones(len(pts))], axis=1)
    rays_c = rays_u @ upright_from_cam_rotation(pitch_deg, roll_deg)  # row-wise R_cam_from_upright x
    in_front = rays_c[:, 2] > 0
    z = np.where(np.abs(rays_c[:, 2]) < 1e-300, 1e-300, rays_c[:, 2])
    return camera.img_from_cam(rays_c[:, :2] / z[:, None]), in_front


def upright_bearings(camera: Camera, keypoints: object, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Unit bearing vectors in the upright frame (y = gravity) of (N, 2) real-image keypoints.

    Returns:
        (N, 3) unit vectors ``R_upright_from_cam · normalize(x, y, 1)``; never degenerate, so
        solvers can use them even for rays above 90° from the virtual optical axis.
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    rays = camera.bearings_from_img(keypoints)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return rays @ upright_from_cam_rotation(pitch_deg, roll_deg).T


def rectified_camera(camera: Camera) -> Camera:
    """The virtual upright camera of :func:`rectify_keypoints`: same ``K`` and size, no distortion."""
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    return Camera(CameraModel.PINHOLE, camera.width, camera.height, (fx, fy, cx, cy))
