"""Images as stored: EXIF orientation ignored on every read path (files, bytes, pictures, a whole
localization), and truncated or damaged PNG/JPEG files refused, never decoded into grey rows."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from planarloc.cli.main import main
from planarloc.features.images import decode_gray, image_problem, read_bgr, read_gray
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.tum import read_tum_trajectory


def jpeg_with_orientation(pixels: np.ndarray, path: Path, orientation: int) -> Path:
    """A JPEG of ``pixels`` (as stored) whose EXIF says 'display rotated/flipped' (tag 0x0112)."""
    image = Image.fromarray(pixels if pixels.ndim == 2 else cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB))
    exif = image.getexif()
    exif[0x0112] = orientation
    image.save(path, exif=exif.tobytes(), quality=98)
    return path


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_is_ignored_by_every_reader(tmp_path, orientation) -> None:
    stored = np.zeros((40, 60), np.uint8)
    stored[:10, :20] = 255  # a bright block in the stored top-left corner
    path = jpeg_with_orientation(stored, tmp_path / "o.jpg", orientation)
    assert (
        cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).shape != stored.shape or orientation == 3
    )  # OpenCV rotates
    for gray in (
        read_gray(path),
        decode_gray(path.read_bytes()),
        cv2.cvtColor(read_bgr(path), cv2.COLOR_BGR2GRAY),
    ):
        assert gray.shape == (40, 60)
        assert gray[:10, :20].mean() > 240 and gray[30:, 40:].mean() < 15


def test_a_query_jpeg_with_orientation_3_localizes_as_stored(tiny_world, tmp_path) -> None:
    """The issue's case: a JPEG saying 'rotate 180°' with a camera describing the stored pixels
    gave a success 180° off. Pixels as stored: the pose is right."""
    db = tmp_path / "map.db"
    assert main(["map", "build", str(tiny_world / "map"), "-f", "tum", "--out", str(db)]) == 0
    query = sorted((tiny_world / "query" / "rgb").glob("*.png"))[2]
    jpg = jpeg_with_orientation(cv2.imread(str(query), cv2.IMREAD_COLOR), tmp_path / "q.jpg", 3)
    camera = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    out = tmp_path / "poses.txt"
    assert (
        main(
            [
                "localize",
                "--map",
                str(db),
                str(jpg),
                "--camera",
                camera,
                "--structure",
                "tracks",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    record = json.loads((tmp_path / "poses.txt.json.d" / "q.jpg.json").read_text())
    assert record["success"], record["status"]
    times, world_from_cam = read_tum_trajectory(tiny_world / "query" / "groundtruth.txt")
    truth = world_from_cam[2].inverse()
    t_err, r_err = pose_errors(Pose.from_quat_wxyz(record["quat_wxyz"], record["t"]), truth)
    assert t_err < 0.25 and r_err < 5


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_and_damaged_files_are_refused(tmp_path, ext) -> None:
    pixels = np.random.default_rng(0).integers(0, 255, (120, 160), np.uint8)
    data = cv2.imencode(ext, pixels)[1].tobytes()
    assert image_problem(data) is None
    cut = data[: len(data) // 2]  # (OpenCV may decode a cut JPEG with grey rows: it must not get that far)
    for broken in (cut, data[:-2], data[:200]):
        path = tmp_path / f"broken{ext}"
        path.write_bytes(broken)
        with pytest.raises(InputError, match=r"broken\.(png|jpg): cannot read image: truncated"):
            read_gray(path)
        with pytest.raises(InputError, match="cannot decode: truncated"):
            decode_gray(broken, "upload.png")
    if ext == ".png":  # one flipped bit in the pixel data: the chunk's CRC says so
        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 0x10
        with pytest.raises(InputError, match="damaged PNG .* CRC"):
            decode_gray(bytes(flipped))
    with pytest.raises(InputError, match="missing.png: cannot read image"):
        read_gray(tmp_path / "missing.png")
