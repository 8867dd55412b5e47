"""Between ROS 2 messages and planarloc: cameras, poses, covariances, odometry and transforms.

Nothing here imports rclpy: the functions take and return plain values (message objects are
read by their fields), so they are tested without a ROS installation.

Frames and conventions (``b_from_a`` maps points of ``a`` to ``b``, docs/conventions.md):

- a ROS transform or pose of ``child`` in ``parent`` is ``parent_from_child``;
- ``/planarloc/pose`` is ``map_from_base`` (or ``map_from_camera`` without base → camera);
- ROS covariances of a ``PoseWithCovariance`` are row-major 6×6 over ``(x, y, z, roll, pitch, yaw)``:
  the position in the parent frame and a **rotation vector about the parent's fixed axes**
  (``parent_from_child' = (Exp(φ) R, p + δp)``), the convention of ``geometry_msgs`` ("fixed-axis
  representation"), of AMCL and of ``robot_localization``.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import skew
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.rosbag import camera_from_info

#: CameraInfo distortion models taken (sensor_msgs/distortion_models.hpp names)
PLUMB_BOB, RATIONAL_POLYNOMIAL, EQUIDISTANT = "plumb_bob", "rational_polynomial", "equidistant"


def camera_from_camera_info(msg: Any, rectified: bool = False) -> Camera:
    """A :class:`Camera` from a ``sensor_msgs/CameraInfo``.

    ``plumb_bob`` (and ``rational_polynomial`` with k3..k6 = 0) → ``OPENCV`` (``PINHOLE`` without
    distortion), ``equidistant`` → ``OPENCV_FISHEYE`` (``D = (k1, k2, k3, k4)``, OpenCV's
    ``cv2.fisheye``, as ROS' image_pipeline). ``rectified`` (an ``image_rect`` topic): the projection
    matrix ``P``, no distortion.

    Raises:
        InputError: another distortion model, or coefficients the models above do not have.
    """
    model = str(getattr(msg, "distortion_model", "")).strip().lower()
    D = np.asarray(getattr(msg, "d", []), dtype=float).reshape(-1)
    if model == EQUIDISTANT and not rectified:  # a fisheye projection even with D = 0
        if D.size not in (0, 4):
            raise InputError(f"CameraInfo: the equidistant model takes 4 coefficients (k1 k2 k3 k4), got {D.size}")
        K = np.asarray(msg.k, dtype=float).reshape(3, 3)
        return Camera("OPENCV_FISHEYE", int(msg.width), int(msg.height),
                      (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *(D if D.size else np.zeros(4))))
    if model == RATIONAL_POLYNOMIAL and D.size >= 5 and not np.any(D[4:]):
        model = PLUMB_BOB
    if model not in ("", PLUMB_BOB) and np.any(D) and not rectified:
        raise InputError(f"CameraInfo distortion model {model!r} is not supported (plumb_bob, equidistant, or "
                         "rational_polynomial with k3..k6 = 0); use a rectified image topic")
    return camera_from_info(msg if str(msg.distortion_model) == PLUMB_BOB else _PlumbBob(msg), rectified)


@dataclass(frozen=True)
class _PlumbBob:
    """A CameraInfo whose zero or dropped coefficients read as plumb_bob."""

    msg: Any

    def __getattr__(self, name: str) -> Any:
        return PLUMB_BOB if name == "distortion_model" else getattr(self.msg, name)


def stamp_seconds(stamp: Any) -> float:
    """A ``builtin_interfaces/Time`` in seconds."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def stamp_parts(seconds: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in seconds (for a ``builtin_interfaces/Time``)."""
    ns = int(round(seconds * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def pose_from_ros(position: Any, orientation: Any) -> Pose:
    """``parent_from_child`` from a ROS position/translation and quaternion (x, y, z, w fields).

    Raises:
        InputError: a zero or non-finite quaternion.
    """
    q = np.array([orientation.w, orientation.x, orientation.y, orientation.z], dtype=float)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-9:
        raise InputError(f"invalid quaternion (w, x, y, z) = {q.tolist()}")
    return Pose.from_quat_wxyz(q, [position.x, position.y, position.z])


def ros_from_pose(pose: Pose) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """``((x, y, z), (qx, qy, qz, qw))`` of ``parent_from_child``: the child's origin in the
    parent and its orientation, as a ROS pose or transform holds them."""
    w, x, y, z = (float(v) for v in pose.quat_wxyz)
    return (float(pose.t[0]), float(pose.t[1]), float(pose.t[2])), (x, y, z, w)


def ros_covariance_of_child(parent_from_frame: Pose, covariance: np.ndarray, frame_from_child: Pose) -> np.ndarray:
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
