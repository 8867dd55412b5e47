"""ROS messages and planarloc values, one conversion each: cameras and ``sensor_msgs/CameraInfo``,
poses and transforms, frame names and stamps.

Shared by the bag reader and writer (:mod:`planarloc.io.rosbag`) and the ROS 2 node and its
replay (:mod:`planarloc.ros2`), so that a message means the same recorded or live. Messages are
read by their fields (rclpy's, rosbags' ROS 2 types, ROS 1 types with upper-case ``K``, ``D``,
``P``): nothing here imports rclpy or rosbags.

CameraInfo (``sensor_msgs/distortion_models.hpp`` names, case-insensitive), first that applies:

- a rectified image topic (:func:`rectified_topic`) with a projection matrix: ``P`` as a PINHOLE
  (rectified images have no distortion);
- ``equidistant`` / ``fisheye``: OPENCV_FISHEYE (``D = k1 k2 k3 k4``, OpenCV's ``cv2.fisheye``, as
  ROS' image_pipeline), also with ``D`` all zero or empty (a fisheye projection without
  distortion is not a pinhole);
- ``D`` empty or all zero (any other model): PINHOLE;
- ``plumb_bob`` / ``rational_polynomial`` with ``D = k1 k2 p1 p2 [k3 [k4 k5 k6]]`` and
  ``k3..k6 = 0``: OPENCV;
- otherwise an error.

Writing (:func:`camera_info_fields`) gives each camera model the CameraInfo that reads back as
the same camera (SIMPLE_RADIAL and RADIAL as the OPENCV with their coefficients).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from planarloc.geometry.camera import Camera, CameraModel
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError

#: CameraInfo distortion models: OpenCV's radial-tangential, and cv2.fisheye's (equidistant)
RADTAN_MODELS = ("plumb_bob", "rational_polynomial")
FISHEYE_MODELS = ("equidistant", "fisheye")
#: the hint of an unsupported CameraInfo (the bag reader adds its camera option)
RECTIFY_HINT = "use a rectified image topic"


def rectified_topic(topic: str) -> bool:
    """Whether an image topic carries rectified images: a name part starting with ``rect`` after a
    ``/`` or ``_`` (``image_rect``, ``image_rect_color``, ``/left/rect``, ``rectified``), as
    image_proc names them (not ``/direct_cam``)."""
    return re.search(r"(?:^|[/_])rect", str(topic)) is not None


def _field(msg: Any, name: str) -> np.ndarray:
    """A CameraInfo array field: ROS 2's lower-case name, else ROS 1's upper-case one."""
    value = getattr(msg, name, None)
    if value is None:
        value = getattr(msg, name.upper(), [])
    return np.asarray(value, dtype=float).reshape(-1)


def camera_from_camera_info(msg: Any, rectified: bool = False, hint: str = RECTIFY_HINT) -> Camera:
    """A :class:`Camera` from a ``sensor_msgs/CameraInfo`` (rules in the module docstring).

    Args:
        msg: the message (fields ``width``, ``height``, ``distortion_model``, ``k``/``K`` (9,),
            ``d``/``D`` (N,), ``p``/``P`` (12,)).
        rectified: the images are rectified (:func:`rectified_topic` of the image topic): ``P``.
        hint: how to get past an unsupported model, appended to the error.

    Raises:
        InputError: a distortion model or coefficients none of the camera models has, naming the
            model and ``D``.

    Example:
        >>> camera_from_camera_info(info)   # distortion_model 'fisheye', D = 0   # doctest: +SKIP
        Camera(model=OPENCV_FISHEYE, ...)
    """
    K, D, P = _field(msg, "k"), _field(msg, "d"), _field(msg, "p")
    w, h = int(msg.width), int(msg.height)
    model = str(getattr(msg, "distortion_model", "")).strip().lower()
    if K.size != 9:
        raise InputError(f"CameraInfo: K has {K.size} values, expected 9 (row-major 3x3)")
    if rectified and P.size == 12 and P[0] > 0:
        return Camera.from_K(P.reshape(3, 4)[:, :3], w, h)
    K = K.reshape(3, 3)
    if model in FISHEYE_MODELS:
        if D.size and (D.size < 4 or np.any(D[4:])):
            raise InputError(
                f"CameraInfo distortion model {model!r} takes 4 coefficients (D = k1 k2 k3 k4), got "
                f"{D.tolist()}; {hint}"
            )
        k = D[:4] if D.size else np.zeros(4)
        return Camera("OPENCV_FISHEYE", w, h, (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *k))
    if not np.any(D):
        return Camera.from_K(K, w, h)
    if model in RADTAN_MODELS and D.size >= 4 and not np.any(D[4:]):
        return Camera.from_K(K, w, h, D[:4])
    raise InputError(
        f"CameraInfo distortion model {model!r} with D = {D.tolist()} is not supported (plumb_bob or "
        f"rational_polynomial with k3..k6 = 0, equidistant/fisheye with 4 coefficients); {hint}"
    )


def camera_info_distortion(camera: Camera) -> tuple[str, np.ndarray]:
    """``(distortion_model, D)`` of a CameraInfo for a camera: ``equidistant`` with ``k1 k2 k3 k4``
    (4,) for OPENCV_FISHEYE; ``plumb_bob`` with ``k1 k2 p1 p2 k3`` (5,), k3 = 0, for the pinhole,
    radial and OPENCV models."""
    if camera.model == CameraModel.OPENCV_FISHEYE:
        return "equidistant", np.asarray(camera.distortion, dtype=float).reshape(4)
    return "plumb_bob", np.concatenate([np.asarray(camera.distortion, dtype=float).reshape(4), np.zeros(1)])


def camera_info_fields(camera: Camera) -> dict[str, Any]:
    """The CameraInfo fields of a camera, ROS 2 names: ``width``, ``height``, ``distortion_model``,
    ``d`` (4,) or (5,), ``k`` (9,), ``r`` (9,) identity, ``p`` (12,) ``[K | 0]`` (lists of floats).
    :func:`camera_from_camera_info` reads them back as the same camera."""
    (fx, fy), (cx, cy) = (float(v) for v in camera.focal), (float(v) for v in camera.principal_point)
    model, D = camera_info_distortion(camera)
    return {
        "width": int(camera.width),
        "height": int(camera.height),
        "distortion_model": model,
        "d": [float(v) for v in D],
        "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    }


def frame_name(name: object) -> str:
    """A TF frame name without its leading ``/`` (ROS 1 names had one)."""
    return str(name).lstrip("/")


def pose_from_ros(position: Any, orientation: Any) -> Pose:
    """``parent_from_child`` from a ROS position/translation and quaternion (``x, y, z, w`` fields).

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


def transform_edge(tf: Any) -> tuple[str, str, Pose]:
    """``(parent, child, parent_from_child)`` of a ``geometry_msgs/TransformStamped``.

    Raises:
        InputError: a bad quaternion, naming the edge.
    """
    parent, child = frame_name(tf.header.frame_id), frame_name(tf.child_frame_id)
    try:
        return parent, child, pose_from_ros(tf.transform.translation, tf.transform.rotation)
    except InputError as exc:
        raise InputError(f"transform {parent} -> {child}: {exc}") from None


def stamp_seconds(stamp: Any) -> float:
    """A ``builtin_interfaces/Time`` in seconds."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def stamp_parts(seconds: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in seconds (for a ``builtin_interfaces/Time``)."""
    ns = round(seconds * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000
