"""Between ROS 2 messages and planarloc: the node's frames, covariances, odometry and transforms.

Nothing here imports rclpy: the functions take and return plain values (message objects are
read by their fields), so they are tested without a ROS installation. The message conversions
shared with ROS bags (CameraInfo, poses, transforms, stamps) are :mod:`planarloc.io.ros_messages`'s,
imported here.

Frames and conventions (``b_from_a`` maps points of ``a`` to ``b``, docs/conventions.md):

- a ROS transform or pose of ``child`` in ``parent`` is ``parent_from_child``;
- ``/planarloc/pose`` is ``map_from_base`` (or ``map_from_camera`` without base → camera);
- ``map`` is z-up (REP-103/105) by default: ``map_from_world`` (:func:`map_from_world_from_gravity`)
  is the rotation from the map's world (the frame of its poses, e.g. KITTI's first camera, y
  down) that puts the map's gravity along −z; ``x_map = R · x_world``, no translation;
- ROS covariances of a ``PoseWithCovariance`` are row-major 6×6 over ``(x, y, z, roll, pitch, yaw)``:
  the position in the parent frame and a **rotation vector about the parent's fixed axes**
  (``parent_from_child' = (Exp(φ) R, p + δp)``), the convention of ``geometry_msgs`` ("fixed-axis
  representation"), of AMCL and of ``robot_localization``.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from planarloc.geometry.epipolar import skew
from planarloc.geometry.pose import Pose
from planarloc.io.ros_messages import (  # noqa: F401  (the node's message conversions: one layer, in io)
    camera_from_camera_info,
    pose_from_ros,
    ros_from_pose,
    stamp_parts,
    stamp_seconds,
    transform_edge,
)
from planarloc.robust.pair_matches import unit_gravity


def ros_covariance_of_child(
    parent_from_frame: Pose, covariance: np.ndarray, frame_from_child: Pose
) -> np.ndarray:
    """ROS-order covariance of ``parent_from_child = parent_from_frame · frame_from_child`` (a rigid
    offset, e.g. the base of a camera) from that of ``parent_from_frame``.

    The rotation vector about the parent's axes is the same; the child's origin
    ``p = c + R a`` moves by ``δc + φ × (R a) = δc − [R a]× φ``.
    """
    lever = parent_from_frame.R @ frame_from_child.t
    J = np.eye(6)
    J[:3, 3:] = -skew(lever[None])[0]
    out = J @ np.asarray(covariance, dtype=float) @ J.T
    return 0.5 * (out + out.T)


def map_from_world_from_gravity(g_world: object) -> Pose:
    """The rotation ``map_from_world`` from a map's world to its z-up, gravity-aligned ``map`` frame
    (REP-103 axes, REP-105 ``map``): the same origin, gravity along −z.

    Args:
        g_world: (3,) gravity (pointing down) in the world frame, any non-zero length (the map's
            :class:`~planarloc.gravity.world.GravityReport` ``g_world``).

    Returns:
        ``Pose(R, 0)`` with ``x_map = R · x_world``. The rows of ``R`` are the map's axes in world
        coordinates: ``z = −g/|g|`` (up); ``x`` = the world's x axis projected into the ground plane
        (``e_x − (e_x · z) z``, normalised), or the world's y axis projected when the world's x is
        within 45° of vertical (``|e_x · z| > √½``; then ``|e_y · z| < √½``); ``y = z × x``. A
        world that is already z-up gives the identity; the heading (yaw) of the map is the world's.

    Raises:
        InputError: a zero or non-finite ``g_world``.

    Example:
        KITTI and the generated worlds (``g_world = +y``: x right, y down, z forward):
        ``R = [[1, 0, 0], [0, 0, 1], [0, −1, 0]]``: map x = world x, map y = world z (forward),
        map z = −world y (up).

        >>> map_from_world_from_gravity([0, 1, 0]).R.astype(int).tolist()
        [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    """
    up = -unit_gravity("g_world", g_world)
    axis = np.eye(3)[0] if abs(up[0]) <= np.sqrt(0.5) else np.eye(3)[1]
    x = axis - (axis @ up) * up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(up, x), up])
    return Pose(R, np.zeros(3))


def ros_covariance_of_parent(new_from_parent: Pose, covariance: np.ndarray) -> np.ndarray:
    """ROS-order covariance of ``new_from_child = new_from_parent · parent_from_child`` (a fixed
    change of the parent frame, e.g. ``map_from_world``) from that of ``parent_from_child``.

    Args:
        new_from_parent: the fixed transform (its translation does not matter).
        covariance: (6, 6) over (position in the parent, rotation vector about the parent's axes).

    Returns:
        (6, 6) ``A C Aᵀ`` with ``A = blockdiag(R, R)``, ``R = new_from_parent.R``: the position
        moves by ``R δp`` and ``R Exp(φ) Rᵀ = Exp(R φ)``, so both blocks rotate by ``R``.
    """
    A = np.kron(np.eye(2), new_from_parent.R)
    out = A @ np.asarray(covariance, dtype=float) @ A.T
    return 0.5 * (out + out.T)


def map_pose_of_child(
    world_from_camera: Pose, covariance: np.ndarray, camera_from_child: Pose, map_from_world: Pose
) -> tuple[Pose, np.ndarray]:
    """The published pose: ``map_from_child = map_from_world · world_from_camera · camera_from_child``
    and its ROS-order covariance.

    Args:
        world_from_camera: the camera's pose in the map's world.
        covariance: (6, 6) ROS-order covariance of ``world_from_camera`` (position in the world,
            rotation vector about the world's axes; ``SequenceEstimate.covariance``).
        camera_from_child: the rigid offset of the published frame (the base; identity for the
            camera itself).
        map_from_world: the published frame's rotation from the world (:func:`map_from_world_from_gravity`;
            identity for ``map_frame_convention`` ``world``).

    Returns:
        ``(map_from_child, (6, 6) covariance)``: :func:`ros_covariance_of_child` through the lever
        arm, then :func:`ros_covariance_of_parent` into ``map``.
    """
    world_from_child = world_from_camera @ camera_from_child
    cov = ros_covariance_of_child(world_from_camera, covariance, camera_from_child)
    return map_from_world @ world_from_child, ros_covariance_of_parent(map_from_world, cov)


def map_from_odom(map_from_base: Pose, odom_from_base: Pose) -> Pose:
    """AMCL's ``map → odom`` transform: ``map_from_odom = map_from_base · odom_from_base⁻¹``,
    both at the image's stamp, so that ``map_from_odom · odom_from_base(t)`` follows the
    odometry between fixes."""
    return map_from_base @ odom_from_base.inverse()


@dataclass
class OdometryBuffer:
    """Recent ``odom_from_child`` samples of ``nav_msgs/Odometry``, looked up at an image's stamp.

    Attributes:
        horizon_s: samples older than this before the newest are forgotten.
    """

    horizon_s: float = 10.0
    stamps: list[float] = field(default_factory=list)
    poses: list[Pose] = field(default_factory=list)
    child_frame: str = ""
    odom_frame: str = ""

    def add(self, stamp: float, odom_from_child: Pose, odom_frame: str = "", child_frame: str = "") -> None:
        """Add a sample (out-of-order samples are inserted in place)."""
        i = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(i, stamp)
        self.poses.insert(i, odom_from_child)
        self.odom_frame, self.child_frame = odom_frame or self.odom_frame, child_frame or self.child_frame
        cut = bisect.bisect_left(self.stamps, self.stamps[-1] - self.horizon_s)
        if cut:
            del self.stamps[:cut], self.poses[:cut]

    def at(self, stamp: float, tolerance_s: float) -> Pose | None:
        """``odom_from_child`` at ``stamp``: interpolated between the two samples around it (linear
        position, slerp rotation) when they are at most ``2 tolerance_s`` apart, else the nearest
        sample within ``tolerance_s``; None without one."""
        if not self.stamps:
            return None
        i = bisect.bisect_left(self.stamps, stamp)
        tolerance_s += 1e-9  # stamps are nanoseconds: 0.3 - 0.2 is within 0.1
        if 0 < i < len(self.stamps) and self.stamps[i] - self.stamps[i - 1] <= 2 * tolerance_s:
            t0, t1 = self.stamps[i - 1], self.stamps[i]
            a, b = self.poses[i - 1], self.poses[i]
            s = 0.0 if t1 <= t0 else (stamp - t0) / (t1 - t0)
            R = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.R, b.R])))([s]).as_matrix()[0]
            return Pose(R, (1 - s) * a.t + s * b.t)
        near = [j for j in (i - 1, i) if 0 <= j < len(self.stamps)]
        j = min(near, key=lambda k: abs(self.stamps[k] - stamp))
        return self.poses[j] if abs(self.stamps[j] - stamp) <= tolerance_s else None


class TransformTree:
    """The latest ``parent_from_child`` of every edge seen on ``/tf`` and ``/tf_static`` (no
    time interpolation: it serves rigid mounts such as base → camera)."""

    def __init__(self) -> None:
        self._edges: dict[str, tuple[str, Pose]] = {}

    def add(self, parent: str, child: str, parent_from_child: Pose) -> None:
        self._edges[child.lstrip("/")] = (parent.lstrip("/"), parent_from_child)

    def add_many(self, edges: Iterable[tuple[str, str, Pose]]) -> None:
        for parent, child, pose in edges:
            self.add(parent, child, pose)

    def _to_root(self, frame: str) -> list[tuple[str, Pose]]:
        """``[(frame, root_from_frame)...]`` along the chain from ``frame`` up to its root."""
        out, pose, seen = [(frame, Pose.identity())], Pose.identity(), {frame}
        while frame in self._edges:
            parent, parent_from_frame = self._edges[frame]
            if parent in seen:
                break
            pose = parent_from_frame @ pose
            frame = parent
            seen.add(frame)
            out.append((frame, pose))
        return out

    def lookup(self, target: str, source: str) -> Pose | None:
        """``target_from_source``, through their common ancestor; None when not connected."""
        target, source = target.lstrip("/"), source.lstrip("/")
        up_source = dict(self._to_root(source))  # ancestor -> ancestor_from_source
        for ancestor, ancestor_from_target in self._to_root(target):
            if ancestor in up_source:
                return ancestor_from_target.inverse() @ up_source[ancestor]
        return None
