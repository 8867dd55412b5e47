"""Posed images written as a KITTI odometry sequence (``image_l/``, ``poses.txt``, ``calib.txt``,
optionally ``times.txt``), for tests of the KITTI paths on generated data."""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.map.posed_image import PosedImage


def kitti_row(values: object) -> str:
    """One line of a KITTI text file: the values, full precision."""
    return " ".join(f"{v:.17g}" for v in np.ravel(values)) + "\n"


def write_kitti_sequence(
    frames: Sequence[PosedImage],
    root: Path,
    times: Sequence[float] | None = None,
    world_from_kitti: Pose | None = None,
) -> Path:
    """``frames`` (one pinhole camera) as the KITTI sequence ``root``: images ``image_l/<k>.png``,
    their poses (camera-to-world rows of ``poses.txt``; in the KITTI world ``world_from_kitti``
    relates to the frames' world, default the same), ``calib.txt`` and ``times.txt`` when
    ``times`` are given. Returns ``root``."""
    (root / "image_l").mkdir(parents=True)
    world_from_kitti = Pose.identity() if world_from_kitti is None else world_from_kitti
    for k, im in enumerate(frames):
        shutil.copy(im.path, root / "image_l" / f"{k:06d}.png")
    (root / "poses.txt").write_text(
        "".join(kitti_row((im.cam_from_world @ world_from_kitti).inverse().matrix) for im in frames)
    )
    fx, fy, cx, cy = frames[0].camera.params
    (root / "calib.txt").write_text(kitti_row([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]]))
    if times is not None:
        (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))
    return root
