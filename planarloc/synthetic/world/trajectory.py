"""Planar robot trajectories: camera centres at a fixed height, rotating about gravity only.

Pose convention (the paper's, same as ``planarloc.geometry.rotation_from_yaw``): an upright
camera with yaw ``θ`` has ``cam_from_world`` rotation

    R = R_y(θ) = [[cos θ, 0, -sin θ], [0, 1, 0], [sin θ, 0, cos θ]]

and translation ``t = -R c`` for the camera centre ``c = (x, -height, z)`` (world y points
down, floor at y = 0). Its optical axis (camera z) in world coordinates is the third row of
R, ``(sin θ, 0, cos θ)``: ``θ`` is the heading measured from world +z towards world +x, and
the camera's right (x) axis is ``(cos θ, 0, -sin θ)``. A path is a pair ``(xz, yaw)`` of
(N, 2) positions in the floor plane and (N,) yaws in radians.
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.planar import rotation_from_yaw


def yaw_rotation(yaw: float | np.ndarray) -> np.ndarray:
    """(..., 3, 3) ``cam_from_world`` rotations R_y(yaw) of upright cameras (see module docstring):
    the paper's eq. (1), checked against SciPy in ``tests/geometry``."""
    return rotation_from_yaw(np.asarray(yaw, dtype=np.float64))


def heading_of(R: np.ndarray) -> np.ndarray:
    """(N,) heading angles of the optical axes of (N, 3, 3) ``cam_from_world`` rotations (yaw if upright)."""
    R = np.asarray(R, dtype=np.float64)
    return np.arctan2(R[..., 2, 0], R[..., 2, 2])


def planar_poses(
    xz: np.ndarray, yaw: np.ndarray, camera_height: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` poses of upright cameras.

    Args:
        xz: (N, 2) camera positions on the floor plane.
        yaw: (N,) headings in radians.
        camera_height: height of the optical centre above the floor, metres (> 0): one
            value, or (N,) values, one per pose.

    Returns:
        R: (N, 3, 3) rotations, t: (N, 3) translations.
    """
    xz = np.asarray(xz, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    if len(xz) != len(yaw):
        raise ValueError(f"planar_poses: {len(xz)} positions but {len(yaw)} yaws")
    height = (
        np.broadcast_to(np.asarray(camera_height, dtype=np.float64), (len(xz),))
        if np.ndim(camera_height) == 0
        else np.asarray(camera_height, dtype=np.float64)
    )
    if height.shape != (len(xz),) or not np.all(height > 0):
        raise ValueError(f"camera_height must be positive, one value or one per pose, got {camera_height!r}")
    centers = np.column_stack([xz[:, 0], -height, xz[:, 1]])
    R = yaw_rotation(yaw)
    t = -np.einsum("nij,nj->ni", R, centers)
    return R, t


def height_profile(
    base_m: float, drop_m: float, wobble_m: float, count: int, cycles: float = 2.0
) -> np.ndarray:
    """(count,) camera heights ``base - drop - wobble · sin(2π · cycles · i / count)`` in metres."""
    i = np.arange(count)
    return base_m - drop_m - wobble_m * np.sin(2 * np.pi * cycles * i / max(count, 1))


def camera_centers(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) world positions ``-R^T t`` of cameras with (N, 3, 3) rotations and (N, 3) translations."""
    return -np.einsum("nji,nj->ni", np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))


def ellipse_loop(
    center_xz: tuple[float, float], radii_xz: tuple[float, float], count: int, phase: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A closed loop on an axis-aligned ellipse, heading along the direction of travel.

    Args:
        center_xz: ellipse centre.
        radii_xz: semi-axes along x and z (> 0).
        count: number of poses, evenly spaced in the ellipse parameter.
        phase: offset of the first pose, in fractions of the spacing (0.5 = midway).

    Returns:
        xz (count, 2) and yaw (count,): the loop runs from +x towards +z around the centre.
    """
    if count < 1 or min(radii_xz) <= 0:
        raise ValueError(f"ellipse_loop needs count >= 1 and positive radii, got {count}, {radii_xz}")
    angle = 2 * np.pi * (np.arange(count) + phase) / count
    xz = np.column_stack(
        [center_xz[0] + radii_xz[0] * np.cos(angle), center_xz[1] + radii_xz[1] * np.sin(angle)]
    )
    tangent = np.column_stack([-radii_xz[0] * np.sin(angle), radii_xz[1] * np.cos(angle)])
    return xz, np.arctan2(tangent[:, 0], tangent[:, 1])


def straight_line(
    start_xz: tuple[float, float], end_xz: tuple[float, float], count: int
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` evenly spaced poses from ``start_xz`` to ``end_xz`` (both included), heading along the line.

    Returns:
        xz (count, 2) and yaw (count,).
    """
    start, end = np.asarray(start_xz, dtype=np.float64), np.asarray(end_xz, dtype=np.float64)
    if count < 2 or np.linalg.norm(end - start) < 1e-6:
        raise ValueError(
            f"straight_line needs count >= 2 and distinct end points, got {count}, {start_xz}, {end_xz}"
        )
    frac = np.linspace(0.0, 1.0, count)
    d = end - start
    return start + frac[:, None] * d, np.full(count, np.arctan2(d[0], d[1]))


WOBBLE_CYCLES = 3.0  # periods of a path's yaw wobble from start to end


def offset_path(
    xz: np.ndarray,
    yaw: np.ndarray,
    lateral_m: float,
    yaw_offset_rad: float,
    yaw_wobble_rad: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A path shifted sideways and turned, to imitate a second run with a different viewpoint.

    Args:
        xz, yaw: (N, 2) and (N,) reference path.
        lateral_m: shift along each pose's right axis ``(cos yaw, -sin yaw)`` (negative: left).
        yaw_offset_rad: constant yaw added to every pose.
        yaw_wobble_rad: amplitude of an extra sinusoidal yaw, ``WOBBLE_CYCLES`` periods along the path.

    Returns:
        xz (N, 2), yaw (N,).
    """
    xz = np.asarray(xz, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    right = np.column_stack([np.cos(yaw), -np.sin(yaw)])
    wobble = yaw_wobble_rad * np.sin(2 * np.pi * WOBBLE_CYCLES * np.arange(len(yaw)) / max(len(yaw), 1))
    return xz + lateral_m * right, yaw + yaw_offset_rad + wobble


def densify(xz: np.ndarray, closed: bool, step_m: float = 0.05) -> np.ndarray:
    """(M, 2) points at most ``step_m`` apart along the polyline through (N, 2) ``xz`` (closed: back
    to the start)."""
    xz = np.asarray(xz, dtype=np.float64).reshape(-1, 2)
    if len(xz) < 2:
        return xz.copy()
    ends = np.vstack([xz[1:], xz[:1]]) if closed else xz[1:]
    pts = [xz[:1]]
    for a, b in zip(xz[: len(ends)], ends, strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_m)))
        f = np.arange(1, n + 1)[:, None] / n
        pts.append(a + f * (b - a))
    return np.vstack(pts)
