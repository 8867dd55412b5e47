"""One ROS message layer (:mod:`planarloc.io.ros_messages`): the same CameraInfo gives the same
camera live (an rclpy message, as the node converts it) and recorded (a ROS 2 bag written with
rosbags, read by ``read_rosbag_images``), and what the replay publishes reads back as its camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
sensor_msgs = pytest.importorskip(
    "sensor_msgs.msg", reason="the ROS 2 messages (pip install 'planarloc[ros2]')"
)

from planarloc.geometry.camera import Camera  # noqa: E402
from planarloc.geometry.validation import InputError  # noqa: E402
from planarloc.io import FormatError  # noqa: E402
from planarloc.io.ros_messages import camera_info_fields, rectified_topic  # noqa: E402
from planarloc.io.rosbag import read_rosbag_images  # noqa: E402
from planarloc.ros2.conversions import camera_from_camera_info  # noqa: E402
from planarloc.ros2.replay import fill_camera_info  # noqa: E402
from planarloc.ros2.settings import NodeSettings  # noqa: E402

W, H = 32, 24
K = [30.0, 0.0, 15.5, 0.0, 31.0, 11.5, 0.0, 0.0, 1.0]
P = [28.0, 0.0, 16.0, 0.0, 0.0, 28.0, 12.0, 0.0, 0.0, 0.0, 1.0, 0.0]  # rectified: another K


def _live(model: str, d: list[float], topic: str) -> Camera:
    msg = sensor_msgs.CameraInfo(
        width=W, height=H, distortion_model=model, d=d, k=K, p=P, r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    )
    return camera_from_camera_info(msg, rectified=NodeSettings(map="m.db", image_topic=topic).rectified)


def _recorded(tmp_path: Path, model: str, d: list[float], topic: str) -> Camera:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="cam"
    )
    info = T["sensor_msgs/msg/CameraInfo"](
        header=header,
        height=H,
        width=W,
        distortion_model=model,
        d=np.array(d, dtype=float),
        k=np.array(K),
        r=np.eye(3).reshape(-1),
        p=np.array(P),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    pixels = np.random.default_rng(0).integers(0, 255, (H, W), dtype=np.uint8)
    image = T["sensor_msgs/msg/Image"](
        header=header, height=H, width=W, encoding="mono8", is_bigendian=0, step=W, data=pixels.reshape(-1)
    )
    bag = tmp_path / "bag"
    with Writer(bag, version=9) as writer:
        for name, msgtype, msg in (
            ("/cam/camera_info", "sensor_msgs/msg/CameraInfo", info),
            (topic, "sensor_msgs/msg/Image", image),
        ):
            conn = writer.add_connection(name, msgtype, typestore=ts)
            writer.write(conn, 5_000_000_000, ts.serialize_cdr(msg, msgtype))
    return read_rosbag_images(bag, image_topic=topic, image_dir=tmp_path / "img")[0].camera


@pytest.mark.parametrize(
    "model, d, topic, expected",
    [
        ("plumb_bob", [0.0] * 5, "/cam/image_raw", Camera("PINHOLE", W, H, (30, 31, 15.5, 11.5))),
        (
            "plumb_bob",
            [0.1, -0.05, 0.001, 0.002, 0.0],
            "/cam/image_raw",
            Camera("OPENCV", W, H, (30, 31, 15.5, 11.5, 0.1, -0.05, 0.001, 0.002)),
        ),
        (
            "rational_polynomial",
            [0.1, -0.05, 0, 0, 0, 0, 0, 0],
            "/cam/image_raw",
            Camera("OPENCV", W, H, (30, 31, 15.5, 11.5, 0.1, -0.05, 0, 0)),
        ),
        (
            "equidistant",
            [0.01, -0.02, 0.003, -0.001],
            "/cam/image_raw",
            Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0.01, -0.02, 0.003, -0.001)),
        ),
        # a fisheye without distortion is still a fisheye (was PINHOLE live, OPENCV_FISHEYE from a bag)
        (
            "fisheye",
            [0.0] * 4,
            "/cam/image_raw",
            Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0, 0, 0, 0)),
        ),
        (
            "fisheye",
            [0.01, -0.02, 0.003, -0.001],
            "/cam/image_raw",
            Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0.01, -0.02, 0.003, -0.001)),
        ),
        (
            "equidistant",
            [],
            "/cam/image_raw",
            Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0, 0, 0, 0)),
        ),
        # rectified topics take P, whatever the distortion (was any name containing "rect" for bags)
        (
            "equidistant",
            [0.01, -0.02, 0.003, -0.001],
            "/cam/image_rect",
            Camera("PINHOLE", W, H, (28, 28, 16, 12)),
        ),
        (
            "plumb_bob",
            [0.1, 0, 0, 0, 0],
            "/cam/left/image_rect_color",
            Camera("PINHOLE", W, H, (28, 28, 16, 12)),
        ),
        (
            "plumb_bob",
            [0.1, 0.0, 0.0, 0.0, 0.0],
            "/cam/direct/image",
            Camera("OPENCV", W, H, (30, 31, 15.5, 11.5, 0.1, 0, 0, 0)),
        ),
    ],
)
def test_the_same_camera_info_gives_the_same_camera_live_and_recorded(
    tmp_path: Path, model: str, d: list[float], topic: str, expected: Camera
) -> None:
    assert _live(model, d, topic) == expected
    assert _recorded(tmp_path, model, d, topic) == expected


@pytest.mark.parametrize(
    "model, d",
    [("plumb_bob", [0.1, 0.0, 0.0, 0.0, 0.3]), ("fisheye", [0.1, 0.2]), ("kannala_brandt8", [0.1] * 8)],
)
def test_an_unsupported_camera_info_is_the_same_error_live_and_recorded(
    tmp_path: Path, model: str, d: list
) -> None:
    with pytest.raises(InputError, match=f"CameraInfo distortion model '{model}'") as live:
        _live(model, d, "/cam/image_raw")
    with pytest.raises(FormatError) as recorded:
        _recorded(tmp_path, model, d, "/cam/image_raw")
    assert str(live.value).split("; ")[0] in str(recorded.value)  # the same sentence, before the hints


@pytest.mark.parametrize(
    "camera",
    [
        Camera("PINHOLE", W, H, (30, 31, 15.5, 11.5)),
        Camera("OPENCV", W, H, (30, 31, 15.5, 11.5, 0.1, -0.05, 0.001, 0.002)),
        Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0, 0, 0, 0)),
        Camera("OPENCV_FISHEYE", W, H, (30, 31, 15.5, 11.5, 0.01, -0.02, 0.003, -0.001)),
    ],
)
def test_what_the_replay_publishes_reads_back_as_its_camera(camera: Camera) -> None:
    msg = sensor_msgs.CameraInfo()
    fill_camera_info(msg, camera)
    assert camera_from_camera_info(msg) == camera
    assert msg.distortion_model == camera_info_fields(camera)["distortion_model"]


def test_rectified_topics() -> None:
    assert all(
        map(rectified_topic, ["/cam/image_rect", "/cam/image_rect_color", "/left/rect/image", "rectified"])
    )
    assert not any(map(rectified_topic, ["/cam/image_raw", "/direct_cam/image", "/cam/correct"]))
