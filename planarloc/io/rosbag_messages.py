"""The messages of ROS bags (:mod:`planarloc.io.rosbag`): their type names, how a message and its
stamp are named, ``sensor_msgs/Image`` decoding, the bag options that are not topics
(``camera``, ``base_to_camera``) and the import of the optional ``rosbags`` package."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Literal

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.text import T_XYZW, parse_camera, parse_pose, pose_from_numbers

FORMAT = "ROS bag"
DEFAULT_MAX_DT = 0.05
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE, ODOMETRY)
#: camera encodings read: name -> (channels, dtype, cv2 conversion to BGR or None)
_ENCODINGS = {
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "bgr8": (3, np.uint8, None),
    "8uc3": (3, np.uint8, None),
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR),
}
_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]
#: how to get past an unsupported CameraInfo in a bag
_CAMERA_HINT = "use a rectified image topic or pass the option camera='OPENCV W H fx fy cx cy k1 k2 p1 p2'"


def _is_depth_encoding(enc: str) -> bool:
    """16UC1, 32FC1 and the other generic encodings that are not 8-bit (depth maps, disparities)."""
    enc = enc.strip().lower()
    return enc[:1].isdigit() and enc not in ("8uc1", "8uc3")


def at_stamp(topic: str, ns: int) -> str:
    """``TOPIC at stamp SEC.NANOSEC``: how a message is named in errors and warnings."""
    return f"{topic} at stamp {ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _rosbags() -> Any:
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.typesys
    except ImportError:
        raise InputError(
            "the rosbag format needs the 'rosbags' package: pip install 'planarloc[ros]'"
        ) from None
    import rosbags

    return rosbags


def _stamp_ns(msg: Any, bag_ns: int) -> int:
    header = getattr(msg, "header", None)
    if header is None:
        return int(bag_ns)
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else int(bag_ns)


def parse_transform(value: object, option: str) -> Pose:
    """``'x y z qx qy qz qw'`` (or 7 numbers): the child's pose in the parent frame
    -> ``parent_from_child``."""
    if isinstance(value, Pose):
        return value
    try:
        if isinstance(value, str):
            return parse_pose(value, T_XYZW)
        if not isinstance(value, Iterable):
            raise TypeError(f"'{type(value).__name__}' object is not iterable")
        return pose_from_numbers([float(v) for v in value], T_XYZW)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{option}: {exc}, got {value!r}") from None


def parse_camera_option(value: object) -> Camera:
    """A Camera, or a line ``'MODEL W H PARAMS...'`` (:func:`planarloc.io.text.parse_camera`)."""
    if isinstance(value, Camera):
        return value
    try:
        return parse_camera(value if isinstance(value, str) else "")
    except InputError as exc:
        raise InputError(f"camera={value!r}: {exc}") from None


def decode_image(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as (H, W) gray or (H, W, 3) BGR array (uint8, or uint16 for mono16)."""
    enc = str(msg.encoding).lower()
    if _is_depth_encoding(enc):
        raise InputError(
            f"encoding {msg.encoding!r} is a depth (or other non-camera) image, not a camera image; "
            "choose the camera's image topic with image_topic=TOPIC"
        )
    if enc not in _ENCODINGS:
        raise InputError(
            f"image encoding {msg.encoding!r} is not supported (supported: {', '.join(_ENCODINGS)})"
        )
    channels, dtype, conversion = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if h < 1 or w < 1 or data.size < h * step or step < w * channels * item:
        raise InputError(
            f"image message: {data.size} bytes do not hold {h} rows of step {step} ({w}x{h} {enc})"
        )
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, : w * channels * item])
    order: Literal[">", "<"] = ">" if int(getattr(msg, "is_bigendian", 0)) else "<"
    img = rows.view(np.dtype(dtype).newbyteorder(order)).astype(dtype).reshape(h, w, channels)
    img = img[:, :, 0] if channels == 1 else img
    return cv2.cvtColor(img, conversion) if conversion is not None else img
