"""ROS bags (ROS 1 ``.bag``, ROS 2 sqlite3 and mcap) as posed-image datasets, via ``rosbags``.

Needs the optional ``rosbags`` package (pure Python, no ROS install): ``pip install 'planarloc[ros]'``.

What is read (``root`` is a ``.bag`` file, a folder of ``.bag`` files read as one recording, a
ROS 2 bag folder with ``metadata.yaml``, or a ``.db3`` / ``.mcap`` file inside one):

- images: ``image_topic`` (``sensor_msgs/Image`` in a camera encoding — mono8, mono16, rgb8,
  bgr8, rgba8, bgra8, or the generic 8UC1 / 8UC3 — or ``sensor_msgs/CompressedImage`` jpeg/png).
  Depth and other non-camera encodings (16UC1, 32FC1, ``compressedDepth``, ...) are refused with
  the topic named. Optional when the bag has a single image topic.
  Each image is written once to ``image_dir`` (default: a cache folder in the temp directory
  keyed by the bag's path, size and mtime): raw images as lossless PNG, compressed images as
  their stored bytes (no re-encoding). The name of a frame is ``<topic>/<sec>.<nanosec>.<ext>``
  with the header stamp (the bag's receive time when the stamp is zero).
- intrinsics, first that applies: the ``camera`` option (a Camera or a line
  ``'PINHOLE W H fx fy cx cy'``); the first ``sensor_msgs/CameraInfo`` of ``camera_info_topic``
  (or of the bag's only CameraInfo topic), converted as the ROS 2 node converts a live one
  (:func:`planarloc.io.ros_messages.camera_from_camera_info`): PINHOLE (no distortion), OPENCV
  (``plumb_bob`` or ``rational_polynomial`` with k3..k6 = 0) or OPENCV_FISHEYE (``equidistant`` or
  ``fisheye``: D = k1 k2 k3 k4, OpenCV's ``cv2.fisheye``, also with D = 0); for a rectified image
  topic (a name part starting with ``rect``: ``image_rect``, ``image_rect_color``) the projection
  matrix P is used (rectified images have no distortion).
- poses, either ``pose_topic`` (``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped`` or
  ``nav_msgs/Odometry``: the pose of a frame in the world, x_world = R x_frame + t), or the
  ``/tf`` + ``/tf_static`` chain from ``tf_parent`` (the world, e.g. ``map``) down to ``tf_child``.
  Each image takes, per transform, the sample with the nearest header stamp within ``max_dt``
  seconds (no interpolation, as the TUM reader); frames without one are skipped with a warning.

Pairing by stamps can only be right when stamps tell frames apart, so duplicates are never
guessed: images that share a header stamp are skipped (a warning per message, naming its topic
and stamp), and pose samples (of the pose topic or of a ``/tf`` edge) that share a stamp but not
their pose are dropped (a warning per message); equal duplicates count once. Every error about a
message names its topic and stamp.

The camera pose: when the posed frame is the robot base rather than the camera's optical frame
(z forward, x right, y down; ROS ``*_optical_frame``), the base-to-camera transform is composed
with it: ``base_to_camera`` if given (``'x y z qx qy qz qw'``, the camera's pose in the base frame,
the argument order of ``static_transform_publisher``), else the ``/tf_static`` chain from the posed
frame (``tf_child`` or the Odometry ``child_frame_id``) to the image's ``header.frame_id``. If
neither exists and the frames differ, the pose is taken as the camera's, with a warning.

:func:`write_rosbag` writes posed images as a bag in the same layout (tests, conversions).

This module reads; the message types and image decoding are in :mod:`planarloc.io.rosbag_messages`,
pose samples and the ``/tf`` buffer in :mod:`planarloc.io.rosbag_poses`, the writer in
:mod:`planarloc.io.rosbag_write` (their public names are importable from here too).
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from planarloc.features.images import (
    ImageFormatError,
    check_image_pixels,
    declared_size,
    image_size_from_header,
)
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.format_error import FormatError
from planarloc.io.output import write_file
from planarloc.io.ros_messages import (
    camera_from_camera_info,
    frame_name,
    pose_from_ros,
    rectified_topic,
)
from planarloc.io.rosbag_messages import (  # noqa: F401  (re-exported: the reader's public names)
    _CAMERA_HINT,
    _ENCODINGS,
    _PNG,
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DEFAULT_MAX_DT,
    FORMAT,
    IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    POSE_TYPES,
    POSE_WITH_COVARIANCE,
    TF_MESSAGE,
    _is_depth_encoding,
    _rosbags,
    _stamp_ns,
    at_stamp,
    decode_image,
    parse_camera_option,
    parse_transform,
)
from planarloc.io.rosbag_poses import TfBuffer, distinct_samples
from planarloc.io.rosbag_topics import BagTopics, pick_topic
from planarloc.io.rosbag_write import POSE_MESSAGES, STORAGES, write_rosbag  # noqa: F401  (re-exported)
from planarloc.io.tum import associate_timestamps
from planarloc.map.posed_image import PosedImage
from planarloc.map.settings import cache_dir

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BagImage:
    """One image of a bag, decoded to a file (no pose).

    Attributes:
        name: ``<topic>/<sec>.<nanosec>.<ext>``, unique within the bag.
        path: the image file in the image folder.
        camera: intrinsics.
        index: position among the image topic's messages (0-based, before ``every``).
        timestamp: header stamp in seconds.
        frame_id: the image's ``header.frame_id`` (its optical frame), without a leading '/'.
    """

    name: str
    path: Path
    camera: Camera
    index: int
    timestamp: float
    frame_id: str


def bag_paths(root: Path) -> list[Path]:
    """The paths ``rosbags.highlevel.AnyReader`` opens for ``root`` (see the module docstring)."""
    root = Path(root)
    if root.is_file() and root.suffix == ".bag":
        return [root]
    if root.is_file() and root.suffix in (".db3", ".mcap") and (root.parent / "metadata.yaml").is_file():
        return [root.parent]
    if root.is_dir() and (root / "metadata.yaml").is_file():
        return [root]
    if root.is_dir():
        bags = sorted(root.glob("*.bag"))
        if bags:
            return bags
    if not root.exists():
        raise FormatError(
            root, None, "no such file or folder; expected a ROS 1 .bag file or a ROS 2 bag folder"
        )
    raise FormatError(
        root,
        None,
        "expected a ROS 1 .bag file, a folder of .bag files, or a ROS 2 bag folder with metadata.yaml",
    )


def default_image_dir(paths: Sequence[Path], image_topic: str) -> Path:
    """The cache folder of a bag's decoded images (temp dir, keyed by path, size, mtime and topic)."""
    h = hashlib.sha1(image_topic.encode())
    for p in paths:
        files = sorted(f for f in Path(p).rglob("*") if f.is_file()) if Path(p).is_dir() else [Path(p)]
        for f in files:
            st = f.stat()
            h.update(f"{f.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return cache_dir("bags") / f"{Path(paths[0]).stem}-{h.hexdigest()[:12]}"


def _shared_stamps(images: Sequence[BagImage], topic: str, action: str) -> set[int]:
    """Indices of the images whose header stamp another image has too (each warned, with ``action``)."""
    count: dict[float, int] = {}
    for im in images:
        count[im.timestamp] = count.get(im.timestamp, 0) + 1
    shared = {i for i, im in enumerate(images) if count[im.timestamp] > 1}
    for i in sorted(shared):
        im = images[i]
        where = at_stamp(topic, int(round(im.timestamp * 1e9)))
        logger.warning(
            "%s (%s): %d images share this header stamp; %s", where, im.name, count[im.timestamp], action
        )
    return shared


@dataclass
class _BagContent:
    image_topic: str
    images: list[BagImage]
    pose_times: list[float]
    poses: list[Pose]
    pose_frame: str | None
    tf: TfBuffer


@dataclass(frozen=True)
class _ImageSelection:
    """Which images of a bag are read, with which camera, and where they are unpacked (the
    options of :func:`read_rosbag`)."""

    image_topic: str | None
    camera_info_topic: str | None
    camera: object
    every: int
    image_dir: str | Path | None


def _read_bag(root: Path, selection: _ImageSelection, pose_topic: str | None, with_tf: bool) -> _BagContent:
    image_topic, camera_info_topic, camera = (
        selection.image_topic,
        selection.camera_info_topic,
        selection.camera,
    )
    every, image_dir = selection.every, selection.image_dir
    rb = _rosbags()
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise InputError(f"every: expected an integer >= 1, got {every!r}")
    paths = bag_paths(Path(root))
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (rb.highlevel.AnyReaderError, OSError) as exc:
        raise FormatError(root, None, f"cannot open the bag: {exc}") from None
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        img_topic = pick_topic(topics, image_topic, (IMAGE, COMPRESSED_IMAGE), "image_topic", root, True)
        cam = parse_camera_option(camera) if camera is not None else None
        info_topic = None
        if cam is None:
            info_topic = pick_topic(
                topics, camera_info_topic, (CAMERA_INFO,), "camera_info_topic", root, False
            )
            if info_topic is None:
                raise FormatError(
                    root,
                    None,
                    "cannot determine the intrinsics: the bag has no sensor_msgs/CameraInfo topic; pass "
                    "the option camera='PINHOLE W H fx fy cx cy' (localize: --camera)",
                )
        if pose_topic is not None:
            pick_topic(topics, pose_topic, POSE_TYPES, "pose_topic", root, True)
        wanted = {img_topic, info_topic, pose_topic}
        if with_tf:
            wanted |= {t for t, ty in topics.items() if ty == TF_MESSAGE and t in ("/tf", "/tf_static")}
        out_dir = Path(image_dir) if image_dir is not None else default_image_dir(paths, img_topic)
        collector = _BagCollector(
            root, BagTopics(img_topic, info_topic, pose_topic), cam, out_dir, int(every)
        )
        for conn, bag_ns, raw in reader.messages(
            connections=[c for c in reader.connections if c.topic in wanted]
        ):
            collector.add(reader, conn, bag_ns, raw)
    finally:
        reader.close()
    return collector.content()


class _BagCollector:
    """Decodes a bag's messages in order: stores the kept images, takes the camera from CameraInfo,
    collects poses and the tf tree."""

    def __init__(self, root: Path, topics: BagTopics, cam: Camera | None, out_dir: Path, every: int):
        self.root, self.topics, self.cam, self.out_dir, self.every = root, topics, cam, out_dir, every
        self.slug = topics.image.strip("/").replace("/", "_") or "image"
        self.pending: list[tuple[str, Path, int, int, str]] = []  # name, file, index, stamp, frame
        self.pose_times: list[float] = []
        self.poses: list[Pose] = []
        self.pose_frame: str | None = None
        self.tf = TfBuffer()
        self.n_image = 0
        self.names: set[str] = set()

    def add(self, reader: Any, conn: Any, bag_ns: int, raw: bytes) -> None:
        index = -1
        if conn.topic == self.topics.image:
            index = self.n_image
            self.n_image += 1
            if index % self.every:
                return
        elif conn.topic == self.topics.camera_info and self.cam is not None:
            return
        where = at_stamp(conn.topic, int(bag_ns))
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds for a damaged message
            raise FormatError(
                self.root,
                None,
                f"{where} (bag time): cannot decode the {conn.msgtype} message ({type(exc).__name__}: {exc})",
            ) from None
        ns = _stamp_ns(msg, bag_ns)
        try:
            self._take(conn, msg, ns, bag_ns, index)
        except InputError as exc:
            raise FormatError(self.root, None, f"{at_stamp(conn.topic, ns)}: {exc}") from None

    def _take(self, conn: Any, msg: Any, ns: int, bag_ns: int, index: int) -> None:
        if conn.topic == self.topics.image:
            name = f"{self.slug}/{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"
            while name in self.names:
                name += "_"
            self.names.add(name)
            path = _store_image(self.out_dir, name, msg, conn.msgtype)
            self.pending.append(
                (str(path.relative_to(self.out_dir)), path, index, ns, frame_name(msg.header.frame_id))
            )
        elif conn.topic == self.topics.camera_info and self.cam is None:
            self.cam = camera_from_camera_info(msg, rectified_topic(self.topics.image), _CAMERA_HINT)
        elif conn.topic == self.topics.pose:
            p = msg.pose if conn.msgtype == POSE_STAMPED else msg.pose.pose
            self.poses.append(pose_from_ros(p.position, p.orientation))
            self.pose_times.append(ns * 1e-9)
            if conn.msgtype == ODOMETRY:
                self.pose_frame = frame_name(msg.child_frame_id)
        elif conn.msgtype == TF_MESSAGE:
            self.tf.add(msg, conn.topic == "/tf_static", bag_ns)

    def content(self) -> _BagContent:
        """What was read, after checking there are images, a camera, and that it fits the first image."""
        root, img_topic, cam = self.root, self.topics.image, self.cam
        if cam is None:
            raise FormatError(
                root,
                None,
                f"{self.topics.camera_info}: no CameraInfo message in the bag; pass the option camera=...",
            )
        images = [
            BagImage(name, path, cam, index, ns * 1e-9, frame)
            for name, path, index, ns, frame in self.pending
        ]
        if not images:
            raise FormatError(root, None, f"expected messages on {img_topic}, found none")
        try:  # the size from the header: nothing is decoded here (the pixel cap of every image path)
            _fmt, width, height = declared_size(Path(images[0].path).read_bytes())
            check_image_pixels(width, height, f"{images[0].path}")
        except (InputError, OSError) as exc:
            raise FormatError(
                root,
                None,
                f"{at_stamp(img_topic, self.pending[0][3])}: cannot decode the first image "
                f"({images[0].path}): {exc}",
            ) from None
        if (width, height) != (cam.width, cam.height):
            raise FormatError(
                root,
                None,
                f"{img_topic}: images are {width}x{height} but the camera is "
                f"{cam.width}x{cam.height}; check camera_info_topic / camera",
            )
        return _BagContent(img_topic, images, self.pose_times, self.poses, self.pose_frame, self.tf)


def _store_image(out_dir: Path, name: str, msg: Any, msgtype: str) -> Path:
    """Write one image message to ``out_dir`` (once); InputError for a message that is no camera image."""
    if msgtype == COMPRESSED_IMAGE:
        fmt = str(msg.format).lower()
        encoding = fmt.split(";")[0].strip()
        if "compresseddepth" in fmt or _is_depth_encoding(encoding):
            raise InputError(
                f"compressed depth images ({msg.format!r}) are not camera images; choose the camera's "
                "image topic with image_topic=TOPIC"
            )
        data = bytes(msg.data)
        try:
            kind, w, h = image_size_from_header(data)
        except ImageFormatError as exc:
            raise InputError(
                f"the CompressedImage data ({msg.format!r}, {len(data)} bytes) is not a readable JPEG or "
                f"PNG: {exc}"
            ) from None
        check_image_pixels(w, h, f"the CompressedImage data ({msg.format!r}, {len(data)} bytes)")
        path = out_dir / (name + (".png" if kind == "png" else ".jpg"))
        if not path.is_file():
            write_file(path, data)
        return path
    path = out_dir / (name + ".png")
    if not path.is_file():
        img = decode_image(msg)
        ok, buf = cv2.imencode(".png", img, _PNG)
        if not ok:
            raise InputError(f"cannot encode {name} as PNG")
        write_file(path, buf.tobytes())
    return path


def read_rosbag_images(
    root: Path,
    *,
    image_topic: str | None = None,
    camera_info_topic: str | None = None,
    camera: Camera | str | None = None,
    every: int = 1,
    image_dir: str | Path | None = None,
) -> list[BagImage]:
    """The images of a bag (no poses needed), e.g. the queries of ``planarloc localize``.

    Args: as :func:`read_rosbag`.

    Returns:
        One :class:`BagImage` per selected message of ``image_topic``, in message order.
    """
    selection = _ImageSelection(image_topic, camera_info_topic, camera, every, image_dir)
    content = _read_bag(Path(root), selection, pose_topic=None, with_tf=False)
    _shared_stamps(
        content.images,
        content.image_topic,
        "kept under distinct names (their stamps do not tell them apart in time)",
    )
    return content.images


def read_rosbag(
    root: Path,
    *,
    image_topic: str | None = None,
    camera_info_topic: str | None = None,
    camera: Camera | str | None = None,
    pose_topic: str | None = None,
    tf_parent: str | None = None,
    tf_child: str | None = None,
    base_to_camera: str | Sequence[float] | Pose | None = None,
    max_dt: float = DEFAULT_MAX_DT,
    every: int = 1,
    image_dir: str | Path | None = None,
) -> list[PosedImage]:
    """Read a ROS bag as posed images (format in the module docstring).

    Args:
        root: ``.bag`` file, folder of ``.bag`` files, ROS 2 bag folder, or its ``.db3``/``.mcap`` file.
        image_topic: Image or CompressedImage topic (default: the bag's only one).
        camera_info_topic: CameraInfo topic (default: the bag's only one, unless ``camera``).
        camera: intrinsics (Camera or ``'MODEL W H PARAMS...'``); overrides CameraInfo.
        pose_topic: PoseStamped / PoseWithCovarianceStamped / Odometry topic with the world pose
            of the camera or of the base.
        tf_parent, tf_child: instead of ``pose_topic``: the world frame and the posed frame of
            the ``/tf`` + ``/tf_static`` chain.
        base_to_camera: the camera's pose in the posed frame, ``'x y z qx qy qz qw'`` (metres,
            quaternion x y z w); default: from ``/tf_static`` if it links the posed frame to the
            image's frame_id, else none.
        max_dt: largest |image stamp - pose stamp| in seconds.
        every: keep image messages with ``index % every == 0``.
        image_dir: where decoded images are written (default: a cache folder in the temp dir).

    Returns:
        One :class:`PosedImage` per kept image that has a pose; ``index`` = message position,
        ``timestamp`` = header stamp in seconds.

    Raises:
        FormatError: missing/ambiguous topics, undecodable images, no intrinsics, no poses.
        InputError: bad options, or ``rosbags`` not installed.

    Example:
        >>> read_rosbag(Path("run1.bag"), image_topic="/cam/image_raw", pose_topic="/odom")  # doctest: +SKIP
    """
    root = Path(root)
    max_dt = _check_pose_options(pose_topic, tf_parent, tf_child, max_dt)
    base_from_camera = (
        parse_transform(base_to_camera, "base_to_camera") if base_to_camera is not None else None
    )
    selection = _ImageSelection(image_topic, camera_info_topic, camera, every, image_dir)
    content = _read_bag(root, selection, pose_topic=pose_topic, with_tf=True)
    images = content.images
    ambiguous = _shared_stamps(
        images, content.image_topic, "skipped: a pose cannot be paired with one of them"
    )
    times = np.array([im.timestamp for im in images])
    if pose_topic is not None:
        if not content.poses:
            raise FormatError(root, None, f"expected pose messages on {pose_topic}, found none")
        pose_times, poses = distinct_samples(content.pose_times, content.poses, pose_topic)
        idx = associate_timestamps(times, pose_times, max_dt)
        world_from_posed = [poses[i] if i >= 0 else None for i in idx]
        posed_frame = content.pose_frame
    else:
        world_from_posed = content.tf.poses_at(
            frame_name(tf_parent), frame_name(tf_child), times, max_dt, root
        )
        posed_frame = frame_name(tf_child)
    extrinsic = base_from_camera
    if extrinsic is None:
        extrinsic = _static_extrinsic(root, content, posed_frame, pose_topic)
    out = [
        PosedImage(
            name=im.name,
            path=im.path,
            cam_from_world=(w_from_p if extrinsic is None else w_from_p @ extrinsic).inverse(),
            camera=im.camera,
            index=im.index,
            timestamp=im.timestamp,
        )
        for k, (im, w_from_p) in enumerate(zip(images, world_from_posed))
        if w_from_p is not None and k not in ambiguous
    ]
    skipped = sum(w is None for k, w in enumerate(world_from_posed) if k not in ambiguous)
    source = pose_topic or f"tf {tf_parent} -> {tf_child}"
    if not out:
        raise FormatError(
            root,
            None,
            f"expected images with a pose ({source}) within max_dt = {max_dt:g} s, found none "
            f"({len(images)} images); check the topics/frames or raise max_dt",
        )
    if skipped:
        logger.warning(
            "%s: %d of %d images have no pose (%s) within max_dt = %g s and are skipped",
            root,
            skipped,
            len(images),
            source,
            max_dt,
        )
    return out


def _check_pose_options(
    pose_topic: str | None, tf_parent: str | None, tf_child: str | None, max_dt: float
) -> float:
    """Either a pose topic or a full tf chain; returns ``max_dt`` as a float >= 0."""
    if (pose_topic is None) == (tf_parent is None and tf_child is None):
        raise InputError(
            "rosbag: give either the option pose_topic=TOPIC or both tf_parent=FRAME and tf_child=FRAME"
        )
    if pose_topic is None and (tf_parent is None or tf_child is None):
        raise InputError("rosbag: the tf chain needs both tf_parent=FRAME (the world) and tf_child=FRAME")
    try:
        max_dt = float(max_dt)
    except (TypeError, ValueError):
        max_dt = math.nan
    if not np.isfinite(max_dt) or max_dt < 0:
        raise InputError(f"max_dt: expected a number of seconds >= 0, got {max_dt!r}")
    return max_dt


def _static_extrinsic(
    root: Path, content: _BagContent, posed_frame: str | None, pose_topic: str | None
) -> Pose | None:
    """``posed_from_camera`` from ``/tf_static`` when the posed frame and the image frame differ
    (None, with a warning, when it does not link them or the posed frame is unnamed)."""
    images = content.images
    if posed_frame:
        image_frame = images[0].frame_id
        if image_frame and image_frame != posed_frame:
            extrinsic = content.tf.static_chain(posed_frame, image_frame)
            if extrinsic is None:
                logger.warning(
                    "%s: the poses are of frame %r, the images of frame %r, and /tf_static does not link "
                    "them; taking the poses as the camera's (pass base_to_camera='x y z qx qy qz qw' if not)",
                    root,
                    posed_frame,
                    image_frame,
                )
            return extrinsic
    elif images[0].frame_id in content.tf.static:
        logger.warning(
            "%s: %s does not name its posed frame, and /tf_static places the image frame %r below %r; taking "
            "the poses as the camera's (if they are of the base, pass base_to_camera='x y z qx qy qz qw')",
            root,
            pose_topic,
            images[0].frame_id,
            content.tf.static[images[0].frame_id][0],
        )
    return None
