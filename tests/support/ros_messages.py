"""Parts of ROS messages the bag tests write with rosbags' own message classes."""

from __future__ import annotations

import numpy as np


def pinhole_camera_info(types, fx: float, fy: float, cx: float, cy: float, ros1: bool = False) -> dict:
    """The calibration fields of a ``sensor_msgs/CameraInfo`` of a pinhole camera (px), unrectified,
    without binning or region of interest; ROS 1 names the matrices ``K, R, P``, ROS 2 ``k, r, p``.
    ``types``: the rosbags typestore's message classes (``typestore.types``)."""
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0])
    r = np.eye(3).reshape(-1)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0])
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    matrices = dict(zip(("K", "R", "P") if ros1 else ("k", "r", "p"), (k, r, p)))
    return {**matrices, "binning_x": 0, "binning_y": 0, "roi": roi}
