"""What the node makes of a frame before it localizes it, without ROS: its pixels (bad frames are
InputErrors, never crashes) and its camera (CameraInfo, else the map's only camera, else an error)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.ros2.node import NO_CAMERA_INFO, frame_camera, frame_pixels

CAM = Camera("PINHOLE", 320, 240, (250, 250, 160, 120))
OTHER = Camera("PINHOLE", 640, 480, (500, 500, 320, 240))


def _image(pixels: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(
        height=pixels.shape[0],
        width=pixels.shape[1],
        encoding="mono8",
        step=pixels.shape[1],
        is_bigendian=0,
        data=pixels.tobytes(),
    )


def _compressed(data: bytes) -> SimpleNamespace:
    return SimpleNamespace(format="png", data=data)


def test_good_frames_give_their_pixels() -> None:
    pixels = np.random.default_rng(0).integers(0, 255, size=(24, 32), dtype=np.uint8)
    assert np.array_equal(frame_pixels(_image(pixels), compressed=False), pixels)
    png = cv2.imencode(".png", pixels)[1].tobytes()
    assert np.array_equal(frame_pixels(_compressed(png), compressed=True), pixels)


@pytest.mark.parametrize(
    "msg, compressed, message",
    [
        (_image(np.zeros((24, 32), np.uint8)), False, "uniform image .every pixel 0."),
        (_compressed(cv2.imencode(".png", np.zeros((24, 32), np.uint8))[1].tobytes()), True, "uniform image"),
        (_compressed(b""), True, "0 bytes"),
        (_compressed(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40), True, "PNG"),
        (_compressed(b"not an image at all"), True, "CompressedImage"),
        (
            SimpleNamespace(height=24, width=32, encoding="mono8", step=32, is_bigendian=0, data=b""),
            False,
            "bytes",
        ),
    ],
)
def test_bad_frames_are_input_errors(msg: SimpleNamespace, compressed: bool, message: str) -> None:
    with pytest.raises(InputError, match=message):
        frame_pixels(msg, compressed)


def test_a_camera_info_wins_over_the_map() -> None:
    assert frame_camera(OTHER, "", {CAM}, "/cam/info") == (OTHER, "camera_info", "", "")


def test_without_camera_info_the_map_s_only_camera_is_used_with_a_warning() -> None:
    camera, source, error, warning = frame_camera(None, NO_CAMERA_INFO, {CAM}, "/cam/info")
    assert (camera, source, error) == (None, "map", "")  # None: the stream takes the map's camera
    assert warning.startswith(
        "no CameraInfo on /cam/info: using the map's only camera (PINHOLE 320x240, params 250 250 160 120)"
    )


def test_without_camera_info_a_map_with_several_cameras_is_an_error_naming_the_topic() -> None:
    camera, source, error, warning = frame_camera(None, NO_CAMERA_INFO, {CAM, OTHER}, "/cam/info")
    assert camera is None and source == "" and error == warning
    assert error == (
        "no CameraInfo on /cam/info and the map has 2 cameras: publish the camera's CameraInfo on "
        "/cam/info (or set camera_info_topic)"
    )


def test_a_bad_camera_info_is_not_replaced_by_the_map_s_camera() -> None:
    bad = "CameraInfo on /cam/info: distortion model 'kb8' is not supported"
    assert frame_camera(None, bad, {CAM}, "/cam/info") == (None, "", bad, "")
