"""ROS bag reader: bags written by the test (ROS 1, ROS 2 sqlite3 and mcap; Image and
CompressedImage; pose topics and the tf chain with a static base -> camera transform)."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from ros_messages import pinhole_camera_info

pytest.importorskip("rosbags")

from planarloc.geometry.camera import Camera  # noqa: E402
from planarloc.geometry.pose import Pose  # noqa: E402
from planarloc.geometry.validation import InputError  # noqa: E402
from planarloc.io import FormatError, read_dataset  # noqa: E402
from planarloc.io.rosbag import read_rosbag, read_rosbag_images, write_rosbag  # noqa: E402
from planarloc.map.posed_image import PosedImage  # noqa: E402

CAMERA = Camera("PINHOLE", 32, 24, (30.0, 31.0, 15.5, 11.5))
#: camera optical frame in base_link: 0.2 m ahead, 0.9 m up, looking along the base's x axis
BASE_FROM_CAMERA = Pose.from_quat_wxyz([0.5, -0.5, 0.5, -0.5], [0.2, 0.0, 0.9])
BASE_TO_CAMERA_OPTION = "0.2 0 0.9 -0.5 0.5 -0.5 0.5"  # x y z qx qy qz qw of the same transform


def posed_images(tmp: Path, random_poses, n: int = 5, color: bool = True) -> list[PosedImage]:
    rng = np.random.default_rng(1)
    out = []
    for k, pose in enumerate(random_poses(n, 3)):
        shape = (24, 32, 3) if color else (24, 32)
        path = tmp / "src" / f"{k:03d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), rng.integers(0, 256, shape, dtype=np.uint8))
        out.append(PosedImage(f"{k:03d}.png", path, pose, CAMERA, k, timestamp=100.0 + 0.1 * k))
    return out


def bag_path(tmp: Path, storage: str, name: str = "run") -> Path:
    return tmp / (f"{name}.bag" if storage == "rosbag1" else name)


def assert_same(read: list[PosedImage], truth: list[PosedImage]) -> None:
    assert len(read) == len(truth)
    for a, b in zip(read, truth):
        np.testing.assert_allclose(a.cam_from_world.matrix4, b.cam_from_world.matrix4, atol=1e-9)
        assert a.camera == b.camera
        assert a.timestamp == pytest.approx(b.timestamp, abs=1e-9)
        np.testing.assert_array_equal(
            cv2.imread(str(a.path), cv2.IMREAD_UNCHANGED), cv2.imread(str(b.path), cv2.IMREAD_UNCHANGED)
        )


@pytest.mark.parametrize("storage", ["rosbag1", "sqlite3", "mcap"])
@pytest.mark.parametrize("compressed", [False, True])
def test_tf_chain_with_static_camera_round_trip(tmp_path, random_poses, storage, compressed):
    truth = posed_images(tmp_path, random_poses)
    bag = write_rosbag(
        bag_path(tmp_path, storage),
        truth,
        storage=storage,
        compressed=compressed,
        pose_message="tf",
        base_from_camera=BASE_FROM_CAMERA,
    )
    read = read_rosbag(bag, tf_parent="map", tf_child="base_link", image_dir=tmp_path / "img")
    assert_same(read, truth)
    assert read[0].name.startswith("camera_image_raw/100.")
    assert read[0].path.suffix == ".png" and read[0].path.is_relative_to(tmp_path / "img")


@pytest.mark.parametrize("storage", ["rosbag1", "sqlite3"])
@pytest.mark.parametrize("message", ["PoseStamped", "PoseWithCovarianceStamped", "Odometry"])
def test_pose_topics_of_the_base_with_base_to_camera(tmp_path, random_poses, storage, message):
    truth = posed_images(tmp_path, random_poses, color=False)
    bag = write_rosbag(
        bag_path(tmp_path, storage),
        truth,
        storage=storage,
        pose_message=message,
        base_from_camera=BASE_FROM_CAMERA,
    )
    read = read_rosbag(
        bag, pose_topic="/pose", base_to_camera=BASE_TO_CAMERA_OPTION, image_dir=tmp_path / "i"
    )
    assert_same(read, truth)
    if message == "Odometry":  # names its child frame: /tf_static supplies base -> camera
        assert_same(read_rosbag(bag, pose_topic="/pose", image_dir=tmp_path / "i"), truth)


def test_camera_pose_topic_needs_no_extrinsic_and_ros2_file_path_works(tmp_path, random_poses):
    truth = posed_images(tmp_path, random_poses)
    bag = write_rosbag(tmp_path / "run", truth, storage="sqlite3", pose_message="PoseStamped")
    db3 = next(bag.glob("*.db3"))
    assert_same(read_dataset(db3, "rosbag", pose_topic="/pose", image_dir=str(tmp_path / "i")), truth)


def test_every_and_max_dt(tmp_path, random_poses):
    truth = posed_images(tmp_path, random_poses, n=6)
    bag = write_rosbag(tmp_path / "run", truth, storage="sqlite3")
    read = read_rosbag(bag, pose_topic="/pose", every=2, image_dir=tmp_path / "i")
    assert [im.index for im in read] == [0, 2, 4]
    assert_same(read, truth[::2])
    late = write_rosbag(tmp_path / "late", truth, storage="sqlite3", pose_delay=0.03)
    with pytest.raises(FormatError, match="within max_dt = 0.01 s, found none"):
        read_rosbag(late, pose_topic="/pose", max_dt=0.01, image_dir=tmp_path / "l")
    assert_same(read_rosbag(late, pose_topic="/pose", max_dt=0.05, image_dir=tmp_path / "l"), truth)
    with pytest.raises(InputError, match="every"):
        read_rosbag(bag, pose_topic="/pose", every=0)


def test_images_only_and_camera_option(tmp_path, random_poses):
    truth = posed_images(tmp_path, random_poses)
    bag = write_rosbag(tmp_path / "run", truth, storage="mcap", camera_info_topic=None, compressed=True)
    with pytest.raises(FormatError, match="camera="):
        read_rosbag_images(bag, image_dir=tmp_path / "i")
    images = read_rosbag_images(bag, camera="PINHOLE 32 24 30 31 15.5 11.5", image_dir=tmp_path / "i")
    assert [im.camera for im in images] == [CAMERA] * 5
    assert [im.frame_id for im in images] == ["camera_optical_frame"] * 5
    with pytest.raises(FormatError, match="images are 32x24 but the camera is 64x48"):
        read_rosbag_images(bag, camera="PINHOLE 64 48 30 31 15.5 11.5", image_dir=tmp_path / "j")


def test_distorted_camera_info_becomes_opencv(tmp_path, random_poses):
    cam = Camera("OPENCV", 32, 24, (30.0, 31.0, 15.5, 11.5, -0.1, 0.01, 0.001, -0.002))
    truth = [
        PosedImage(p.name, p.path, p.cam_from_world, cam, p.index, p.timestamp)
        for p in posed_images(tmp_path, random_poses, n=2)
    ]
    bag = write_rosbag(tmp_path / "run.bag", truth, storage="rosbag1")
    assert read_rosbag(bag, pose_topic="/pose", image_dir=tmp_path / "i")[0].camera == cam


def test_errors_name_the_option_and_the_choices(tmp_path, random_poses):
    truth = posed_images(tmp_path, random_poses, n=2)
    bag = write_rosbag(
        tmp_path / "run", truth, storage="sqlite3", pose_message="tf", base_from_camera=BASE_FROM_CAMERA
    )
    with pytest.raises(InputError, match="pose_topic=TOPIC or both tf_parent"):
        read_rosbag(bag)
    with pytest.raises(FormatError, match=r"image_topic='/nope': no such topic; topics: .*/camera/image_raw"):
        read_rosbag(bag, image_topic="/nope", tf_parent="map", tf_child="base_link")
    with pytest.raises(FormatError, match="has type sensor_msgs/msg/CameraInfo"):
        read_rosbag(bag, image_topic="/camera/camera_info", tf_parent="map", tf_child="base_link")
    with pytest.raises(
        FormatError, match=r"not an ancestor .* \(frames: base_link, camera_optical_frame, map\)"
    ):
        read_rosbag(bag, tf_parent="odom", tf_child="base_link", image_dir=tmp_path / "i")
    with pytest.raises(InputError, match="base_to_camera: expected 7 numbers"):
        read_rosbag(bag, tf_parent="map", tf_child="base_link", base_to_camera="1 2 3")
    with pytest.raises(FormatError, match="expected a ROS 1 .bag file"):
        read_rosbag(tmp_path / "src", pose_topic="/pose")
    with pytest.raises(InputError, match="exists already"):
        write_rosbag(bag, truth)


def test_pose_of_the_base_without_extrinsic_warns(tmp_path, random_poses, caplog):
    truth = posed_images(tmp_path, random_poses, n=2)
    bag = write_rosbag(
        tmp_path / "run",
        truth,
        storage="sqlite3",
        pose_message="PoseStamped",
        base_from_camera=BASE_FROM_CAMERA,
    )
    with caplog.at_level(logging.WARNING):
        read_rosbag(bag, pose_topic="/pose", image_dir=tmp_path / "i")
    assert "pass base_to_camera" in caplog.text


def _rosbags_own_bag(path: Path, truth: list[PosedImage]) -> Path:
    """A ROS 1 bag written with rosbags' own Writer and message classes, as a robot's driver
    stack records one: rgb8 images on their topic, a CameraInfo per frame, nav_msgs/Odometry of
    the camera's optical frame in the map, bag times after the header stamps."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]

    def header(ns: int, frame: str, seq: int) -> object:
        return Header(seq=seq, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    with Writer(path) as writer:
        images = writer.add_connection("/cam/image_color", "sensor_msgs/msg/Image", typestore=ts)
        infos = writer.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        (fx, fy), (cx, cy) = CAMERA.focal, CAMERA.principal_point
        for seq, im in enumerate(truth):
            ns = int(round(im.timestamp * 1e9))
            rgb = cv2.cvtColor(cv2.imread(str(im.path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            world_from_cam = im.cam_from_world.inverse()
            q, t = world_from_cam.quat_wxyz, world_from_cam.t
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0]),
            )
            zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            msgs = [
                (
                    odom,
                    ns + 2_000_000,
                    T["nav_msgs/msg/Odometry"](
                        header=header(ns + 1_000_000, "map", seq),
                        child_frame_id="cam_optical",
                        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                        twist=T["geometry_msgs/msg/TwistWithCovariance"](
                            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                            covariance=np.zeros(36),
                        ),
                    ),
                ),
                (
                    infos,
                    ns + 3_000_000,
                    T["sensor_msgs/msg/CameraInfo"](
                        header=header(ns, "cam_optical", seq),
                        height=CAMERA.height,
                        width=CAMERA.width,
                        distortion_model="plumb_bob",
                        D=np.zeros(5),
                        **pinhole_camera_info(T, fx, fy, cx, cy, ros1=True),
                    ),
                ),
                (
                    images,
                    ns + 4_000_000,
                    T["sensor_msgs/msg/Image"](
                        header=header(ns, "cam_optical", seq),
                        height=rgb.shape[0],
                        width=rgb.shape[1],
                        encoding="rgb8",
                        is_bigendian=0,
                        step=3 * rgb.shape[1],
                        data=rgb.reshape(-1),
                    ),
                ),
            ]
            for conn, bag_ns, msg in msgs:
                writer.write(conn, bag_ns, ts.serialize_ros1(msg, conn.msgtype))
    return path


def test_a_bag_written_by_rosbags_itself_and_its_ros2_conversion_read_as_the_truth(tmp_path, random_poses):
    from rosbags.convert import convert

    truth = posed_images(tmp_path, random_poses, n=4)
    bag = _rosbags_own_bag(tmp_path / "driver.bag", truth)
    read = read_rosbag(bag, pose_topic="/odom", max_dt=0.002, image_dir=tmp_path / "i1")
    assert_same(read, truth)  # poses, CameraInfo intrinsics, stamps and rgb8 pixels (as BGR)
    assert read[0].name.startswith("cam_image_color/100.")
    ros2 = tmp_path / "driver-ros2"
    convert([bag], ros2, "sqlite3", 8, None, "file", None, None, [], [], [], [])  # rosbags' own converter
    assert_same(read_rosbag(ros2, pose_topic="/odom", max_dt=0.002, image_dir=tmp_path / "i2"), truth)
