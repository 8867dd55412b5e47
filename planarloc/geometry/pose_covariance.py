"""Pose covariances in the two orders planarloc uses (docs/conventions.md, "Pose covariances").

- **Pose-graph order** ``(ω, δc)`` of a ``cam_from_world`` pose: ``R_cw' = exp([ω]×) R_cw`` (a
  rotation of the camera frame, radians), then ``c' = c + δc`` (the centre in the world, metres).
  The stream's pose graph, its motions and its fixes use it.
- **ROS order** ``(δc, φ)`` of ``world_from_camera`` (``geometry_msgs/PoseWithCovariance``,
  :attr:`planarloc.robust.result.PoseEstimate.covariance`): the centre, then a rotation vector
  about the world axes, ``R_wc' = exp([φ]×) R_wc``; ``φ = −R_cwᵀ ω``.
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import check_array


def _reordered(covariance: np.ndarray, J: np.ndarray) -> np.ndarray:
    C = check_array("covariance", covariance, (6, 6), finite=False)
    if not np.all(np.isfinite(C)):
        return np.full((6, 6), np.inf)
    out = J @ C @ J.T
    return 0.5 * (out + out.T)


def ros_covariance(cam_from_world: Pose, covariance: np.ndarray) -> np.ndarray:
    """The pose graph's (6, 6) covariance of a ``cam_from_world`` pose in ROS order.

    Args:
        cam_from_world: the pose the covariance belongs to.
        covariance: (6, 6) in pose-graph order; a non-finite one stays all inf.

    Returns:
        (6, 6) in ROS order.

    Example:
        >>> C = np.diag([1e-4] * 3 + [0.01] * 3)     # 0.57° per axis, 0.1 m per axis
        >>> np.diag(ros_covariance(Pose.identity(), C)).tolist()
        [0.01, 0.01, 0.01, 0.0001, 0.0001, 0.0001]
    """
    J = np.zeros((6, 6))
    J[:3, 3:] = np.eye(3)
    J[3:, :3] = -cam_from_world.R.T
    return _reordered(covariance, J)


def graph_covariance(cam_from_world: Pose, covariance: np.ndarray) -> np.ndarray:
    """The inverse of :func:`ros_covariance`: ROS order to pose-graph order ``(ω, δc)``."""
    J = np.zeros((6, 6))
    J[:3, 3:] = -cam_from_world.R
    J[3:, :3] = np.eye(3)
    return _reordered(covariance, J)


def covariance_stds(covariance: np.ndarray) -> tuple[float, float]:
    """(position std [m], rotation std [deg]) of a pose-graph covariance along its worst axes
    (square roots of the largest eigenvalues of its blocks); (inf, inf) when not finite."""
    if not np.all(np.isfinite(covariance)):
        return float("inf"), float("inf")
    rot = float(np.sqrt(max(np.linalg.eigvalsh(covariance[:3, :3])[-1], 0.0)))
    pos = float(np.sqrt(max(np.linalg.eigvalsh(covariance[3:, 3:])[-1], 0.0)))
    return pos, float(np.degrees(rot))


def displacement_covariance(
    d: np.ndarray, along_std: float, across_std: float, rotation_std: float
) -> np.ndarray:
    """(6, 6) pose-graph covariance of a motion whose centre displacement ``d`` (3,) has
    ``along_std`` (m) along its direction and ``across_std`` across it, and ``rotation_std``
    (rad) per rotation axis; a zero displacement has ``along_std`` on every axis."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * rotation_std**2
    n = float(np.linalg.norm(d))
    if n <= 1e-9:
        cov[3:, 3:] = np.eye(3) * along_std**2
        return cov
    u = np.asarray(d, dtype=float) / n
    P = np.outer(u, u)
    cov[3:, 3:] = along_std**2 * P + across_std**2 * (np.eye(3) - P)
    return cov
