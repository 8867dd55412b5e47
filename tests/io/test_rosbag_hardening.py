"""ROS bags that a careless or broken recorder writes: frames sharing a stamp, pose samples
sharing a stamp, depth topics taken for cameras, short and damaged messages (every error names
its topic and stamp), and every camera model through CameraInfo (fisheye = equidistant)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from ros_messages import pinhole_camera_info

pytest.importorskip("rosbags")

from planarloc.geometry.camera import Camera, CameraModel  # noqa: E402
from planarloc.geometry.pose import Pose  # noqa: E402
from planarloc.io import FormatError  # noqa: E402
from planarloc.io.rosbag import read_rosbag, read_rosbag_images, write_rosbag  # noqa: E402
from planarloc.map.posed_image import PosedImage  # noqa: E402

CAMERA = Camera("PINHOLE", 32, 24, (30.0, 31.0, 15.5, 11.5))


def posed(tmp: Path, n: int, stamps: list[float] | None = None, camera: Camera = CAMERA) -> list[PosedImage]:
    rng = np.random.default_rng(3)
    out = []
    for k in range(n):
        path = tmp / "src" / f"{k:03d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), rng.integers(0, 256, (24, 32), dtype=np.uint8))
        pose = Pose.from_center(np.eye(3), [float(k), 0.0, 0.0])  # frame k at x = k metres
        t = 100.0 + 0.1 * k if stamps is None else stamps[k]
        out.append(PosedImage(f"{k:03d}.png", path, pose, camera, k, timestamp=t))
    return out


@pytest.mark.parametrize("pose_message", ["PoseStamped", "tf"])
def test_frames_sharing_a_stamp_never_get_each_others_pose(tmp_path, caplog, pose_message) -> None:
    """Frames 1 and 2 share a stamp, each with its own pose message at that stamp (1 m apart): both
    are skipped with a warning each; every other frame gets exactly its own pose."""
    truth = posed(tmp_path, 5, stamps=[100.0, 100.1, 100.1, 100.3, 100.4])
    bag = write_rosbag(tmp_path / "dup", truth, storage="sqlite3", pose_message=pose_message)
    options = (
        {"pose_topic": "/pose"}
        if pose_message != "tf"
        else {"tf_parent": "map", "tf_child": "camera_optical_frame"}
    )
    with caplog.at_level(logging.WARNING):
        read = read_rosbag(bag, image_dir=tmp_path / "img", **options)
    assert [im.timestamp for im in read] == pytest.approx([100.0, 100.3, 100.4])
    for im in read:
        k = {100.0: 0, 100.3: 3, 100.4: 4}[round(im.timestamp, 3)]
        np.testing.assert_allclose(im.cam_from_world.center, [float(k), 0, 0], atol=1e-9)
    lines = [r.getMessage() for r in caplog.records]
    shared = [line for line in lines if "share this header stamp" in line]
    assert len(shared) == 2 and all("/camera/image_raw at stamp 100.100000000" in line for line in shared)
    assert sum("pose samples share this stamp" in line for line in lines) == 2  # one per message
    # The same bag read for queries (no poses): both frames kept, warned.
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        frames = read_rosbag_images(bag, image_dir=tmp_path / "q")
    assert len(frames) == 5 and len({f.name for f in frames}) == 5
    assert sum("kept under distinct names" in r.getMessage() for r in caplog.records) == 2


def test_equal_duplicate_pose_samples_count_once(tmp_path, caplog) -> None:
    truth = posed(tmp_path, 3)
    doubled = [truth[0], truth[1], dataclasses.replace(truth[1], name="x.png", index=9), truth[2]]
    bag = write_rosbag(
        tmp_path / "eq", doubled, storage="sqlite3"
    )  # frame 1 and its copy: one stamp, one pose
    with caplog.at_level(logging.WARNING):
        read = read_rosbag(bag, pose_topic="/pose", image_dir=tmp_path / "img")
    assert len(read) == 2  # the two images at one stamp are still ambiguous
    assert not any("pose samples share" in r.getMessage() for r in caplog.records)


# ---- messages that are not camera images, or broken --------------------------------------------------
def custom_bag(path: Path, messages: list[tuple[str, str, int, object]]) -> Path:
    """A ROS 2 bag of (topic, msgtype, stamp ns, message or raw bytes) written with rosbags itself."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    conns: dict[str, object] = {}
    with Writer(path, version=9) as writer:
        for topic, msgtype, ns, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], ns, msg if isinstance(msg, bytes) else ts.serialize_cdr(msg, msgtype))
    return path


def types():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).types


def header(ns: int, frame: str = "cam"):
    T = types()
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame
    )


def image_msg(ns: int, encoding: str, data: np.ndarray, step: int, h: int = 24, w: int = 32):
    return types()["sensor_msgs/msg/Image"](
        header=header(ns),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.ascontiguousarray(data).reshape(-1).view(np.uint8),
    )


def camera_info(ns: int, model: str = "plumb_bob", D=(0.0,) * 5):
    T = types()
    fx, fy, cx, cy = 30.0, 31.0, 15.5, 11.5
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(ns),
        height=24,
        width=32,
        distortion_model=model,
        d=np.array(D, dtype=float),
        **pinhole_camera_info(T, fx, fy, cx, cy),
    )


NS = 5_000_000_123
IMG = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"


@pytest.mark.parametrize(
    "encoding,dtype",
    [("16UC1", np.uint16), ("32FC1", np.float32), ("16SC1", np.int16), ("64FC1", np.float64)],
)
def test_depth_topics_are_refused_naming_topic_and_stamp(tmp_path, encoding, dtype) -> None:
    data = np.ones((24, 32), dtype)
    bag = custom_bag(
        tmp_path / "depth",
        [
            ("/camera/camera_info", INFO, NS, camera_info(NS)),
            ("/depth/image_raw", IMG, NS, image_msg(NS, encoding, data, 32 * data.itemsize)),
        ],
    )
    with pytest.raises(FormatError) as exc:
        read_rosbag_images(bag, image_dir=tmp_path / "i")
    text = str(exc.value)
    assert "/depth/image_raw at stamp 5.000000123" in text and encoding in text and "depth" in text
    assert "image_topic" in text


def test_compressed_depth_and_garbage_are_refused(tmp_path) -> None:
    T = types()
    for k, (fmt, data) in enumerate(
        [
            ("16UC1; compressedDepth", b"\x89PNG\r\n\x1a\n" + b"\0" * 30),
            ("16UC1; png compressed", b"\x89PNG\r\n\x1a\n" + b"\0" * 30),
            ("jpeg", b"not a jpeg at all"),
        ]
    ):
        msg = T["sensor_msgs/msg/CompressedImage"](
            header=header(NS), format=fmt, data=np.frombuffer(data, np.uint8)
        )
        bag = custom_bag(
            tmp_path / f"c{k}",
            [
                ("/camera/camera_info", INFO, NS, camera_info(NS)),
                ("/cam/compressed", "sensor_msgs/msg/CompressedImage", NS, msg),
            ],
        )
        with pytest.raises(FormatError, match="/cam/compressed at stamp 5.000000123"):
            read_rosbag_images(bag, image_dir=tmp_path / f"i{k}")


def test_short_and_damaged_messages_name_topic_and_stamp(tmp_path) -> None:
    short = image_msg(NS, "mono8", np.zeros(100, np.uint8), 32)  # 100 bytes for 24 rows of 32
    bag = custom_bag(
        tmp_path / "short",
        [("/camera/camera_info", INFO, NS, camera_info(NS)), ("/camera/image_raw", IMG, NS, short)],
    )
    with pytest.raises(
        FormatError, match=r"/camera/image_raw at stamp 5.000000123: image message: 100 bytes"
    ):
        read_rosbag_images(bag, image_dir=tmp_path / "i")
    bag = custom_bag(
        tmp_path / "broken",
        [
            ("/camera/camera_info", INFO, NS, camera_info(NS)),
            ("/camera/image_raw", IMG, NS, b"\x00\x01\x00\x00garbage"),
        ],
    )
    with pytest.raises(
        FormatError, match=r"/camera/image_raw at stamp 5.000000123 \(bag time\): cannot decode"
    ):
        read_rosbag_images(bag, image_dir=tmp_path / "j")
    info = camera_info(NS, "plumb_bob", (0.1, 0.0, 0.0, 0.0, 0.3))  # k3 != 0: no supported model
    good = image_msg(NS, "mono8", np.zeros((24, 32), np.uint8), 32)
    bag = custom_bag(tmp_path / "k3", [("/cam/info", INFO, NS, info), ("/camera/image_raw", IMG, NS, good)])
    with pytest.raises(
        FormatError, match=r"/cam/info at stamp 5.000000123: CameraInfo distortion model 'plumb_bob'"
    ):
        read_rosbag_images(bag, image_dir=tmp_path / "k")


@pytest.mark.parametrize("model", ["equidistant", "fisheye"])
def test_equidistant_camera_info_is_opencv_fisheye(tmp_path, model) -> None:
    D = (0.1, -0.02, 0.003, -0.0004)
    good = image_msg(NS, "mono8", np.zeros((24, 32), np.uint8), 32)
    bag = custom_bag(
        tmp_path / "fe",
        [("/cam/info", INFO, NS, camera_info(NS, model, D)), ("/camera/image_raw", IMG, NS, good)],
    )
    cam = read_rosbag_images(bag, image_dir=tmp_path / "i")[0].camera
    assert cam == Camera("OPENCV_FISHEYE", 32, 24, (30.0, 31.0, 15.5, 11.5, *D))


@pytest.mark.parametrize(
    "camera",
    [
        Camera("SIMPLE_PINHOLE", 32, 24, (30.0, 15.5, 11.5)),
        Camera("PINHOLE", 32, 24, (30.0, 31.0, 15.5, 11.5)),
        Camera("SIMPLE_RADIAL", 32, 24, (30.0, 15.5, 11.5, -0.05)),
        Camera("RADIAL", 32, 24, (30.0, 15.5, 11.5, -0.05, 0.01)),
        Camera("OPENCV", 32, 24, (30.0, 31.0, 15.5, 11.5, -0.1, 0.01, 0.001, -0.002)),
        Camera("OPENCV_FISHEYE", 32, 24, (30.0, 31.0, 15.5, 11.5, 0.1, -0.02, 0.003, -0.0004)),
    ],
)
@pytest.mark.parametrize("storage", ["rosbag1", "sqlite3"])
def test_the_bag_writer_writes_each_camera_model_so_that_it_reads_back(tmp_path, camera, storage) -> None:
    assert set(CameraModel) == {
        CameraModel(c)
        for c in ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE")
    }  # every model is tested
    truth = posed(tmp_path, 2, camera=camera)
    bag = write_rosbag(tmp_path / ("run.bag" if storage == "rosbag1" else "run"), truth, storage=storage)
    read = read_rosbag(bag, pose_topic="/pose", image_dir=tmp_path / "img")[0].camera
    if camera.model == CameraModel.OPENCV_FISHEYE:
        assert read == camera
    pts = np.random.default_rng(0).uniform([-0.4, -0.3, 1.0], [0.4, 0.3, 3.0], (50, 3))
    np.testing.assert_allclose(read.img_from_cam(pts), camera.img_from_cam(pts), atol=1e-9)
