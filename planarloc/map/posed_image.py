"""The record every importer produces and every map stores: an image with a known pose."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.gravity.world import WorldDown


@dataclass(frozen=True)
class PosedImage:
    """One image of a dataset with its ground-truth or map pose.

    Attributes:
        name: unique name within its dataset (usually the path relative to the dataset root,
            e.g. ``"image_l/000012.png"``); used as the key in maps and result files.
        path: absolute path of the image file.
        cam_from_world: pose of the camera (``x_cam = R x_world + t``), world units in metres.
        camera: intrinsics.
        index: frame index in the sequence (0-based); ``--every N`` / ``--map-every N`` select
            frames with ``index % N == 0``.
        timestamp: seconds, when the format has one (TUM, OpenLORIS, kapture), else None.
        depth_path: optional depth image (uint16 PNG, metres x ``depth_scale``).
        depth_scale: factor from stored depth values to metres' reciprocal (TUM: 5000).
        world_down: the world's gravity direction when the dataset's format defines one (e.g.
            KITTI: +y of the first camera) or the user gave ``up=``; None = unknown, the map
            estimates it from its poses (:mod:`planarloc.gravity.world`).
    """

    name: str
    path: Path
    cam_from_world: Pose
    camera: Camera
    index: int
    timestamp: float | None = None
    depth_path: Path | None = None
    depth_scale: float = 5000.0
    world_down: WorldDown | None = None
