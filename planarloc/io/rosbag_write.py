"""Writing posed images as a ROS bag (ROS 1 ``.bag``, ROS 2 sqlite3 or mcap), the inverse of
:func:`planarloc.io.rosbag.read_rosbag` (tests, conversions); needs the optional ``rosbags`` package."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.ros_messages import camera_info_fields
from planarloc.io.rosbag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE,
    TF_MESSAGE,
    _rosbags,
)
from planarloc.map.posed_image import PosedImage

STORAGES = ("rosbag1", "sqlite3", "mcap")
POSE_MESSAGES = {
    "PoseStamped": POSE_STAMPED,
    "PoseWithCovarianceStamped": POSE_WITH_COVARIANCE,
    "Odometry": ODOMETRY,
    "tf": TF_MESSAGE,
}


@dataclass(frozen=True)
class BagLayout:
    """What :func:`write_rosbag` writes: storage, topics, message types and frames (see its docstring)."""

    storage: str = "sqlite3"
    compressed: bool = False
    image_topic: str = "/camera/image_raw"
    camera_info_topic: str | None = "/camera/camera_info"
    pose_topic: str = "/pose"
    pose_message: str = "PoseStamped"
    world_frame: str = "map"
    base_frame: str = "base_link"
    camera_frame: str = "camera_optical_frame"
    base_from_camera: Pose | None = None
    pose_delay: float = 0.0

    @property
    def posed_frame(self) -> str:
        return self.base_frame if self.base_from_camera is not None else self.camera_frame


def write_rosbag(
    out: Path, images: Sequence[PosedImage], layout: BagLayout | None = None, **overrides: Any
) -> Path:
    """Write posed images as a ROS bag (the inverse of :func:`read_rosbag`).

    Args:
        out: a new ``.bag`` file (``storage="rosbag1"``) or a new ROS 2 bag folder.
        images: posed images; stamps are their ``timestamp`` (else ``0.1 s * index``).
        layout: a :class:`BagLayout` (None: defaults); keyword ``overrides`` replace its fields,
            e.g. ``write_rosbag(out, images, storage="mcap", compressed=True)``.

    Layout fields:
        storage: ``"rosbag1"``, ``"sqlite3"`` or ``"mcap"``.
        compressed: write ``sensor_msgs/CompressedImage`` (the image files' PNG/JPEG bytes)
            instead of ``sensor_msgs/Image`` (mono8 or bgr8).
        image_topic, camera_info_topic: image and CameraInfo topics (CameraInfo skipped if None;
            the distortion model of :func:`planarloc.io.ros_messages.camera_info_distortion`, every camera
            model).
        pose_topic, pose_message: topic and type (``PoseStamped``, ``PoseWithCovarianceStamped``,
            ``Odometry``) of the poses, or ``"tf"``: the poses go to ``/tf`` as
            ``world_frame -> base_frame`` (``pose_topic`` unused).
        world_frame, base_frame, camera_frame: frame ids.
        base_from_camera: if given, the poses written are the base's (world_from_cam ∘
            camera_from_base) and ``/tf_static`` holds ``base_frame -> camera_frame``; else the
            poses are the camera's (``base_frame`` = ``camera_frame`` in tf mode).
        pose_delay: seconds added to the pose stamps (to exercise time matching).

    Returns:
        ``out``.
    """
    layout = replace(layout or BagLayout(), **overrides)
    _rosbags()
    if layout.storage not in STORAGES:
        raise InputError(f"storage: expected one of {', '.join(STORAGES)}, got {layout.storage!r}")
    if layout.pose_message not in POSE_MESSAGES:
        raise InputError(
            f"pose_message: expected one of {', '.join(POSE_MESSAGES)}, got {layout.pose_message!r}"
        )
    out = Path(out)
    bag = _BagWriter(layout)
    writer, bag.serialize = _open_writer(out, layout.storage, bag.ts)
    with writer:
        bag.writer = writer
        if layout.base_from_camera is not None:
            ns0 = _stamp_of(images[0]) if images else 0
            msg = bag.T[TF_MESSAGE](
                transforms=[
                    bag.transform_msg(ns0, layout.base_frame, layout.camera_frame, layout.base_from_camera)
                ]
            )
            bag.write("/tf_static", TF_MESSAGE, ns0, msg)
        for seq, im in enumerate(images):
            ns = _stamp_of(im)
            bag.write_pose(im, ns, seq)
            if layout.camera_info_topic is not None:
                msg = _camera_info_msg(bag.T, bag.header(ns, layout.camera_frame, seq), im.camera, bag.ros1)
                bag.write(layout.camera_info_topic, CAMERA_INFO, ns, msg)
            bag.write_image(im, ns, seq)
    return out


class _BagWriter:
    """Builds the messages of one bag with its type store and writes them, one connection per topic."""

    def __init__(self, layout: BagLayout):
        from rosbags.typesys import Stores, get_typestore

        self.layout = layout
        self.ros1 = layout.storage == "rosbag1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if TF_MESSAGE not in self.ts.types:  # the noetic store lacks tf2_msgs
            from rosbags.typesys import get_types_from_msg

            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
        self.T = self.ts.types
        self.conns: dict[str, Any] = {}
        self.writer: Any = None
        self.serialize: Any = None

    def write(self, topic: str, msgtype: str, ns: int, msg: Any) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        self.writer.write(self.conns[topic], ns, self.serialize(msg, msgtype))

    def header(self, ns: int, frame: str, seq: int = 0) -> Any:
        kw = {"seq": seq} if self.ros1 else {}
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return self.T["std_msgs/msg/Header"](**kw, stamp=stamp, frame_id=frame)

    def pose_msg(self, p: Pose) -> Any:
        q, t, T = p.quat_wxyz, p.t, self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
            ),
        )

    def transform_msg(self, ns: int, parent: str, child: str, p: Pose) -> Any:
        q, t, T = p.quat_wxyz, p.t, self.T
        return T["geometry_msgs/msg/TransformStamped"](
            header=self.header(ns, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=T["geometry_msgs/msg/Quaternion"](
                    x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
                ),
            ),
        )

    def write_pose(self, im: PosedImage, ns: int, seq: int) -> None:
        """The image's pose (camera's or base's) as the layout's pose message, or on ``/tf``."""
        lay, T = self.layout, self.T
        world_from_cam = im.cam_from_world.inverse()
        world_from_posed = (
            world_from_cam
            if lay.base_from_camera is None
            else world_from_cam @ lay.base_from_camera.inverse()
        )
        pns = ns + int(round(lay.pose_delay * 1e9))
        if lay.pose_message == "tf":
            msg = T[TF_MESSAGE](
                transforms=[self.transform_msg(pns, lay.world_frame, lay.posed_frame, world_from_posed)]
            )
            self.write("/tf", TF_MESSAGE, pns, msg)
            return
        mt = POSE_MESSAGES[lay.pose_message]
        p = self.pose_msg(world_from_posed)
        header = self.header(pns, lay.world_frame, seq)
        if mt == POSE_STAMPED:
            msg = T[mt](header=header, pose=p)
        else:
            cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=np.zeros(36))
            if mt == POSE_WITH_COVARIANCE:
                msg = T[mt](header=header, pose=cov)
            else:
                zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
                twist = T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
                )
                msg = T[mt](header=header, child_frame_id=lay.posed_frame, pose=cov, twist=twist)
        self.write(lay.pose_topic, mt, pns, msg)

    def write_image(self, im: PosedImage, ns: int, seq: int) -> None:
        """The image file as a CompressedImage (its bytes) or an Image (mono8 / bgr8)."""
        lay, T = self.layout, self.T
        header = self.header(ns, lay.camera_frame, seq)
        if lay.compressed:
            data = Path(im.path).read_bytes()
            fmt = "png" if Path(im.path).suffix.lower() == ".png" else "jpeg"
            msg = T[COMPRESSED_IMAGE](header=header, format=fmt, data=np.frombuffer(data, dtype=np.uint8))
            self.write(lay.image_topic, COMPRESSED_IMAGE, ns, msg)
            return
        img = cv2.imread(str(im.path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{im.path}: cannot read image")
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        enc = "mono8" if img.ndim == 2 else "bgr8"
        if img.dtype != np.uint8:
            raise InputError(f"{im.path}: only 8-bit images can be written as sensor_msgs/Image")
        msg = T[IMAGE](
            header=header,
            height=img.shape[0],
            width=img.shape[1],
            encoding=enc,
            is_bigendian=0,
            step=img.shape[1] * (1 if img.ndim == 2 else 3),
            data=np.ascontiguousarray(img).reshape(-1),
        )
        self.write(lay.image_topic, IMAGE, ns, msg)


def _stamp_of(im: PosedImage) -> int:
    t = im.timestamp if im.timestamp is not None else 0.1 * im.index
    return int(round(float(t) * 1e9))


def _camera_info_msg(T: Any, header: Any, cam: Camera, ros1: bool) -> Any:
    """A rosbags CameraInfo of ``cam`` (:func:`planarloc.io.ros_messages.camera_info_fields`)."""
    info = camera_info_fields(cam)
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    arrays = {(k.upper() if ros1 else k): np.asarray(info[k], dtype=float) for k in ("d", "k", "r", "p")}
    return T[CAMERA_INFO](
        header=header,
        height=info["height"],
        width=info["width"],
        distortion_model=info["distortion_model"],
        binning_x=0,
        binning_y=0,
        roi=roi,
        **arrays,
    )


def _open_writer(out: Path, storage: str, ts: Any) -> tuple[Any, Any]:
    if out.exists():
        raise InputError(f"{out}: exists already; a bag is never overwritten")
    if storage == "rosbag1":
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(out), ts.serialize_ros1
    import inspect

    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    kwargs: dict[str, Any] = {}
    params = inspect.signature(Writer2).parameters
    if "version" in params:
        kwargs["version"] = 9
    if "storage_plugin" in params:
        kwargs["storage_plugin"] = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    elif storage == "mcap":
        raise InputError("writing mcap needs rosbags >= 0.10 with the mcap storage plugin")
    return Writer2(out, **kwargs), ts.serialize_cdr
