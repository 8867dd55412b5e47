"""Small generated datasets on disk: textured PNGs with poses, for map build / identity tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from textured_images import textured_image

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.map.posed_image import PosedImage

CAMERA = Camera("PINHOLE", 160, 120, (150.0, 150.0, 80.0, 60.0))


def posed_folder(root: Path, n: int = 4, seed: int = 0, camera: Camera = CAMERA) -> list[PosedImage]:
    """Write ``n`` textured images to ``root/image_l/00000k.png``; poses along the x axis (1 m apart).

    Names are ``image_l/00000k.png`` for every seed, like KITTI sequences: two folders collide.
    """
    rng = np.random.default_rng(seed)
    (root / "image_l").mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(n):
        name = f"image_l/{k:06d}.png"
        cv2.imwrite(str(root / name), textured_image(rng, camera.height, camera.width))
        out.append(
            PosedImage(
                name, (root / name).absolute(), Pose(np.eye(3), np.array([-float(k), 0.0, 0.0])), camera, k
            )
        )
    return out


def shifted(images: list[PosedImage], dx: float) -> list[PosedImage]:
    """The same images with every camera moved by ``dx`` metres along x."""
    import dataclasses

    return [
        dataclasses.replace(im, cam_from_world=Pose(im.cam_from_world.R, im.cam_from_world.t - [dx, 0, 0]))
        for im in images
    ]
