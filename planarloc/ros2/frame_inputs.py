"""The inputs of a camera frame in the ROS 2 node: its camera (a CameraInfo or the map's only camera)
and its pixels (an ``Image`` or a ``CompressedImage``)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

import numpy as np

from planarloc.features.images import decode_gray
from planarloc.geometry.camera import Camera, CameraModel
from planarloc.geometry.validation import InputError
from planarloc.io.rosbag import decode_image

#: why there is no camera yet: no CameraInfo received (the map's only camera is used, :func:`frame_camera`)
NO_CAMERA_INFO = "no CameraInfo received yet"


def frame_camera(
    camera: Camera | None, camera_error: str, map_cameras: Collection[Camera], camera_info_topic: str
) -> tuple[Camera | None, str, str, str]:
    """The camera of the next frame: ``(camera, source, error, warning)``.

    Args:
        camera: the last usable CameraInfo's camera, or None.
        camera_error: why ``camera`` is None: :data:`NO_CAMERA_INFO` (none received yet) or the
            last CameraInfo's problem.
        map_cameras: the map's distinct cameras.
        camera_info_topic: named in the messages.

    Returns:
        ``(camera, "camera_info", "", "")`` with a CameraInfo; ``(None, "map", "", warning)`` while
        none has been received and the map has exactly one camera (None: the stream takes the
        map's; the warning names it); ``(None, "", error, error)`` otherwise (a bad CameraInfo, or
        a map with several cameras: the error says to publish the CameraInfo).
    """
    if camera is not None:
        return camera, "camera_info", "", ""
    if camera_error != NO_CAMERA_INFO:  # a CameraInfo arrived but is not usable
        return None, "", camera_error, ""
    cameras = list(map_cameras)
    if len(cameras) != 1:
        error = (
            f"no CameraInfo on {camera_info_topic} and the map has {len(cameras)} cameras: publish the "
            f"camera's CameraInfo on {camera_info_topic} (or set camera_info_topic)"
        )
        return None, "", error, error
    (only,) = cameras
    warning = (
        f"no CameraInfo on {camera_info_topic}: using the map's only camera ({CameraModel(only.model).value} "
        f"{only.width}x{only.height}, params {' '.join(f'{p:g}' for p in only.params)}); publish the "
        "camera's CameraInfo if the images come from another camera"
    )
    return None, "map", "", warning


def frame_pixels(msg: Any, compressed: bool) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` ((H, W) or (H, W, 3), :func:`~planarloc.io.rosbag.decode_image`)
    or of a ``CompressedImage`` (``compressed``: (H, W) gray).

    Raises:
        InputError: an empty or undecodable image, or a uniform one (every pixel the same, e.g. a
            black frame: nothing to localize).
    """
    if compressed:
        data = bytes(msg.data)
        image = decode_gray(data, f"CompressedImage ({msg.format!r}, {len(data)} bytes)")
    else:
        image = decode_image(msg)
    if image.size and image.min() == image.max():
        raise InputError(f"a uniform image (every pixel {image.flat[0]}): nothing to localize")
    return image
