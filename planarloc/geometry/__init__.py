"""Poses, cameras, the planar motion model and epipolar math (numpy only)."""

from planarloc.geometry.camera import Camera, CameraModel
from planarloc.geometry.planar import (
    essential_from_planar_params,
    planar_params_from_relpose,
    relpose_from_planar_params,
    rotation_from_yaw,
    yaw_from_rotation,
)
from planarloc.geometry.pose import Pose, pose_errors, rotation_error_deg
from planarloc.geometry.validation import InputError

__all__ = [
    "Camera",
    "CameraModel",
    "InputError",
    "Pose",
    "essential_from_planar_params",
    "planar_params_from_relpose",
    "pose_errors",
    "relpose_from_planar_params",
    "rotation_error_deg",
    "rotation_from_yaw",
    "yaw_from_rotation",
]
