"""planarloc: 3D-model-free visual localization under local planar motion.

Conventions: see docs/conventions.md. Poses are ``cam_from_world`` (x_cam = R x_world + t).
"""

from planarloc.geometry import Camera, CameraModel, InputError, Pose

__all__ = ["Camera", "CameraModel", "InputError", "Pose"]
__version__ = "0.1.0"
