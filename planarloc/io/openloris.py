"""OpenLORIS-Scene sequences (Shi et al., ICRA 2020), RealSense D400 colour camera.

Layout of a sequence directory ``root`` (e.g. ``office1-1``)::

    root/
      color.txt          '# comment' lines, then 'timestamp color/<timestamp>.png' per frame
      color/             the colour images
      groundtruth.txt    header '#Time px py pz qx qy qz qw', then one line per sample: the
                         pose of the robot's base_link in the world (world_from_base, metres,
                         quaternion x y z w; planar: z = 0, yaw only)
      aligned_depth.txt  optional 'timestamp filename' list of depth images aligned to colour;
      aligned_depth/     if there is no list, file stems are the timestamps. uint16 PNG,
                         metres = value / 1000
      camera.txt         optional intrinsics line (see planarloc.io.camera_file)

The camera pose is ``world_from_cam = world_from_base ∘ base_from_camera`` with the published
extrinsic ``T_bc`` (``DEFAULT_BASE_FROM_CAMERA``). Intrinsics, first that applies: the
``camera=`` argument, ``camera.txt``, the published d400 colour intrinsics (848x480).
Association with ground truth and depth as for TUM (:func:`planarloc.io.tum.associate_timestamps`):
nearest timestamp within ``max_dt``; frames without a pose are skipped with a warning.

Gravity: the ground-truth world has z up (the robot base moves in its x-y plane), so the format
declares down = −z (:data:`WORLD_DOWN`).
"""

from __future__ import annotations

from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.gravity.world import WorldDown
from planarloc.io.tum import DEFAULT_MAX_DT, RgbdLayout, read_rgbd_sequence, resolve_camera
from planarloc.map.posed_image import PosedImage

FORMAT = "OpenLORIS-Scene"
#: base_link <- colour camera (x_base = R x_cam + t): t = (0.2265, -0.0511, 0.916) m,
#: q(x, y, z, w) = (-0.4968, 0.4999, -0.4951, 0.5082) (normalised here).
DEFAULT_BASE_FROM_CAMERA = Pose.from_quat_wxyz([0.5082, -0.4968, 0.4999, -0.4951], [0.2265, -0.0511, 0.916])
#: RealSense D400 colour intrinsics of OpenLORIS-Scene.
D400_COLOR_CAMERA = Camera("PINHOLE", 848, 480, (611.4510, 611.4857, 433.2040, 249.4730))
OPENLORIS_DEPTH_SCALE = 1000.0
#: The ground-truth world of OpenLORIS-Scene has z up (planar base motion in x-y): down = −z.
WORLD_DOWN = WorldDown((0.0, 0.0, -1.0), "declared", "OpenLORIS-Scene: world z up, down = -z")
LAYOUT = RgbdLayout(FORMAT, "color.txt", "aligned_depth.txt", "aligned_depth")


def read_openloris(
    root: Path,
    *,
    camera: Camera | None = None,
    base_from_camera: Pose | None = DEFAULT_BASE_FROM_CAMERA,
    max_dt: float = DEFAULT_MAX_DT,
    depth_scale: float = OPENLORIS_DEPTH_SCALE,
    check_images: bool = True,
) -> list[PosedImage]:
    """Read an OpenLORIS-Scene sequence (format in the module docstring).

    Args:
        root: sequence directory (with ``color.txt`` and ``groundtruth.txt``).
        camera: colour intrinsics; default ``camera.txt`` if present, else the d400 values.
        base_from_camera: camera extrinsic in base_link (``x_base = R x_cam + t``); ``None``
            if the ground truth already is the camera's pose.
        max_dt: association tolerance in seconds.
        depth_scale: depth PNG value per metre (OpenLORIS: 1000).
        check_images: raise if a listed image does not exist.

    Returns:
        One :class:`PosedImage` per colour frame with a pose, ``index`` = position in
        ``color.txt``, names as listed (``color/<timestamp>.png``).
    """
    root = Path(root)
    preset = None if (root / "camera.txt").is_file() else D400_COLOR_CAMERA
    cam = resolve_camera(root, FORMAT, camera, preset, "pass camera=Camera(...)")
    return read_rgbd_sequence(
        root,
        LAYOUT,
        cam,
        depth_scale=depth_scale,
        base_from_camera=base_from_camera,
        max_dt=max_dt,
        check_images=check_images,
        world_down=WORLD_DOWN,
    )
