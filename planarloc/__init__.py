"""planarloc: 3D-model-free visual localization under local planar motion.

Conventions: see docs/conventions.md. Poses are ``cam_from_world`` (x_cam = R x_world + t).
"""

# First, before numpy loads OpenBLAS: its idle threads stop spinning within a millisecond, not
# 0.1 s, so the next query's feature extraction gets the cores (planarloc.numerics.blas_threads).
from planarloc.numerics.blas_threads import shorten_openblas_spin

shorten_openblas_spin()

# Then, before any numba kernel is defined: numba's cache also on read-only installs.
import planarloc.numerics.kernel_cache
from planarloc.geometry import Camera, CameraModel, InputError, Pose
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import Method, RansacOptions, Structure
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.result import PoseEstimate
from planarloc.version import __version__


def __getattr__(name: str):
    # The pipeline (OpenCV, faiss, SQLite) loads only when used, keeping `import planarloc` light.
    if name in ("Localizer", "LocalizerConfig"):
        from planarloc.localize import localizer

        return getattr(localizer, name)
    raise AttributeError(f"module 'planarloc' has no attribute {name!r}")


__all__ = [
    "Camera",
    "CameraModel",
    "InputError",
    "Localizer",
    "LocalizerConfig",
    "Method",
    "PairMatches",
    "Pose",
    "PoseEstimate",
    "RansacOptions",
    "Structure",
    "estimate_absolute_pose",
]
