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
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from planarloc.features.images import ImageFormatError, check_image_pixels, declared_size, image_size_from_header
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.format_error import FormatError
from planarloc.io.output import write_file
from planarloc.io.ros_messages import (
    camera_from_camera_info,
    camera_info_fields,
    frame_name,
    pose_from_ros,
    rectified_topic,
    transform_edge,
)
from planarloc.io.text import T_XYZW, parse_camera, parse_pose, pose_from_numbers
from planarloc.io.tum import associate_timestamps
from planarloc.map.posed_image import PosedImage
from planarloc.map.settings import cache_dir

logger = logging.getLogger(__name__)

FORMAT = "ROS bag"
DEFAULT_MAX_DT = 0.05
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE, ODOMETRY)
#: camera encodings read: name -> (channels, dtype, cv2 conversion to BGR or None)
_ENCODINGS = {
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "bgr8": (3, np.uint8, None),
    "8uc3": (3, np.uint8, None),
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR),
}
_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]
#: how to get past an unsupported CameraInfo in a bag
_CAMERA_HINT = "use a rectified image topic or pass the option camera='OPENCV W H fx fy cx cy k1 k2 p1 p2'"


def _is_depth_encoding(enc: str) -> bool:
    """16UC1, 32FC1 and the other generic encodings that are not 8-bit (depth maps, disparities)."""
    enc = enc.strip().lower()
    return enc[:1].isdigit() and enc not in ("8uc1", "8uc3")


def at_stamp(topic: str, ns: int) -> str:
    """``TOPIC at stamp SEC.NANOSEC``: how a message is named in errors and warnings."""
    return f"{topic} at stamp {ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _rosbags() -> Any:
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.typesys
    except ImportError:
        raise InputError(
            "the rosbag format needs the 'rosbags' package: pip install 'planarloc[ros]'"
        ) from None
    import rosbags

    return rosbags


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
        raise FormatError(root, None, "no such file or folder; expected a ROS 1 .bag file or a ROS 2 bag folder")
    raise FormatError(
        root, None, "expected a ROS 1 .bag file, a folder of .bag files, or a ROS 2 bag folder with metadata.yaml"
    )


def _stamp_ns(msg: Any, bag_ns: int) -> int:
    header = getattr(msg, "header", None)
    if header is None:
        return int(bag_ns)
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else int(bag_ns)


def parse_transform(value: object, option: str) -> Pose:
    """``'x y z qx qy qz qw'`` (or 7 numbers): the child's pose in the parent frame -> ``parent_from_child``."""
    if isinstance(value, Pose):
        return value
    try:
        if isinstance(value, str):
            return parse_pose(value, T_XYZW)
        return pose_from_numbers([float(v) for v in value], T_XYZW)  # type: ignore[union-attr]
    except (TypeError, ValueError) as exc:
        raise InputError(f"{option}: {exc}, got {value!r}") from None


def parse_camera_option(value: object) -> Camera:
    """A Camera, or a line ``'MODEL W H PARAMS...'`` (:func:`planarloc.io.text.parse_camera`)."""
    if isinstance(value, Camera):
        return value
    try:
        return parse_camera(value if isinstance(value, str) else "")
    except InputError as exc:
        raise InputError(f"camera={value!r}: {exc}") from None


def decode_image(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as (H, W) gray or (H, W, 3) BGR array (uint8, or uint16 for mono16)."""
    enc = str(msg.encoding).lower()
    if _is_depth_encoding(enc):
        raise InputError(f"encoding {msg.encoding!r} is a depth (or other non-camera) image, not a camera image; "
                         "choose the camera's image topic with image_topic=TOPIC")
    if enc not in _ENCODINGS:
        raise InputError(f"image encoding {msg.encoding!r} is not supported (supported: {', '.join(_ENCODINGS)})")
    channels, dtype, conversion = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if h < 1 or w < 1 or data.size < h * step or step < w * channels * item:
        raise InputError(f"image message: {data.size} bytes do not hold {h} rows of step {step} ({w}x{h} {enc})")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, : w * channels * item])
    order = ">" if int(getattr(msg, "is_bigendian", 0)) else "<"
    img = rows.view(np.dtype(dtype).newbyteorder(order)).astype(dtype).reshape(h, w, channels)
    img = img[:, :, 0] if channels == 1 else img
    return cv2.cvtColor(img, conversion) if conversion is not None else img


def default_image_dir(paths: Sequence[Path], image_topic: str) -> Path:
    """The cache folder of a bag's decoded images (temp dir, keyed by path, size, mtime and topic)."""
    h = hashlib.sha1(image_topic.encode())
    for p in paths:
        files = sorted(f for f in Path(p).rglob("*") if f.is_file()) if Path(p).is_dir() else [Path(p)]
        for f in files:
            st = f.stat()
            h.update(f"{f.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return cache_dir("bags") / f"{Path(paths[0]).stem}-{h.hexdigest()[:12]}"


def _pick_topic(topics: dict[str, str], wanted: str | None, types: Sequence[str], option: str, root: Path,
                required: bool) -> str | None:
    if wanted is not None:
        if wanted not in topics:
            raise FormatError(root, None, f"{option}={wanted!r}: no such topic; topics: {_topic_list(topics)}")
        if topics[wanted] not in types:
            raise FormatError(
                root, None, f"{option}={wanted!r} has type {topics[wanted]}, expected one of {', '.join(types)}"
            )
        return wanted
    candidates = sorted(t for t, ty in topics.items() if ty in types)
    if len(candidates) == 1:
        return candidates[0]
    if not required and not candidates:
        return None
    found = ", ".join(candidates) if candidates else "none"
    raise FormatError(
        root, None, f"give the dataset option {option}=TOPIC ({', '.join(types)} topics in the bag: {found})"
    )


def _same_pose(a: Pose, b: Pose, tol: float = 1e-9) -> bool:
    return bool(np.allclose(a.matrix, b.matrix, atol=tol))


def distinct_samples(times: Sequence[float], poses: Sequence[Pose], what: str) -> tuple[list[float], list[Pose]]:
    """The pose samples of one source (a pose topic, a ``/tf`` edge) without ambiguous stamps:
    samples sharing a stamp count once if their poses agree, else all of them are dropped with a
    warning per message (a frame at that time cannot be given the right one)."""
    by_stamp: dict[float, list[int]] = {}
    for i, t in enumerate(times):
        by_stamp.setdefault(float(t), []).append(i)
    keep = []
    for t, idx in by_stamp.items():
        if len(idx) == 1 or all(_same_pose(poses[idx[0]], poses[i]) for i in idx[1:]):
            keep.append(idx[0])
            continue
        for i in idx:
            logger.warning("%s: %d pose samples share this stamp with different poses; none of them is used",
                           at_stamp(what, int(round(t * 1e9))), len(idx))
    keep.sort()
    return [float(times[i]) for i in keep], [poses[i] for i in keep]


def _shared_stamps(images: Sequence[BagImage], topic: str, action: str) -> set[int]:
    """Indices of the images whose header stamp another image has too (each warned, with ``action``)."""
    count: dict[float, int] = {}
    for im in images:
        count[im.timestamp] = count.get(im.timestamp, 0) + 1
    shared = {i for i, im in enumerate(images) if count[im.timestamp] > 1}
    for i in sorted(shared):
        im = images[i]
        where = at_stamp(topic, int(round(im.timestamp * 1e9)))
        logger.warning("%s (%s): %d images share this header stamp; %s", where, im.name, count[im.timestamp], action)
    return shared


def _topic_list(topics: dict[str, str]) -> str:
    return ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"


class _TfBuffer:
    """Static and time-stamped transforms ``parent_from_child`` per edge (child -> parent)."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, Pose]] = {}
        self.dynamic: dict[str, tuple[str, list[float], list[Pose]]] = {}

    def add(self, msg: Any, static: bool, bag_ns: int = 0) -> None:
        for tf in msg.transforms:
            parent, child, pose = transform_edge(tf)
            if static:
                if child in self.static and not _same_pose(self.static[child][1], pose):
                    logger.warning("/tf_static: %s -> %s is published twice with different transforms; the later "
                                   "is used", parent, child)
                self.static[child] = (parent, pose)
            else:
                entry = self.dynamic.setdefault(child, (parent, [], []))
                entry[1].append(_stamp_ns(tf, bag_ns) * 1e-9)
                entry[2].append(pose)

    def parent(self, child: str) -> str | None:
        if child in self.static:
            return self.static[child][0]
        if child in self.dynamic:
            return self.dynamic[child][0]
        return None

    def chain(self, parent: str, child: str) -> list[str] | None:
        """Frames from ``child`` up to (excluding) ``parent``, or None if ``parent`` is not an ancestor."""
        out, frame = [], child
        while frame != parent:
            out.append(frame)
            frame = self.parent(frame)  # type: ignore[assignment]
            if frame is None or len(out) > 1000:
                return None
        return out

    def static_chain(self, parent: str, child: str) -> Pose | None:
        """``parent_from_child`` if ``child`` hangs below ``parent`` through static transforms only."""
        chain = self.chain(parent, child)
        if chain is None or any(f not in self.static for f in chain):
            return None
        pose = Pose.identity()
        for f in chain:
            pose = self.static[f][1] @ pose
        return pose

    def frames(self) -> list[str]:
        names = set(self.static) | set(self.dynamic)
        names |= {p for p, _ in self.static.values()} | {e[0] for e in self.dynamic.values()}
        return sorted(names)

    def poses_at(self, parent: str, child: str, times: np.ndarray, max_dt: float,
                 root: Path) -> list[Pose | None]:
        """``parent_from_child`` at each time (None where a dynamic edge has no sample within max_dt)."""
        chain = self.chain(parent, child)
        if chain is None:
            raise FormatError(
                root, None, f"tf_parent={parent!r} is not an ancestor of tf_child={child!r} in /tf and /tf_static "
                f"(frames: {', '.join(self.frames()) or 'none'})"
            )
        out: list[Pose | None] = [Pose.identity() for _ in times]
        for frame in chain:
            if frame in self.static:
                edge = self.static[frame][1]
                out = [None if p is None else edge @ p for p in out]
                continue
            parent, stamps, poses = self.dynamic[frame]
            stamps, poses = distinct_samples(stamps, poses, f"/tf {parent} -> {frame}")
            idx = associate_timestamps(times, stamps, max_dt)
            out = [None if p is None or i < 0 else poses[i] @ p for p, i in zip(out, idx)]
        return out


@dataclass
class _BagContent:
    image_topic: str
    images: list[BagImage]
    pose_times: list[float]
    poses: list[Pose]
    pose_frame: str | None
    tf: _TfBuffer


def _read_bag(
    root: Path,
    *,
    image_topic: str | None,
    camera_info_topic: str | None,
    camera: object,
    pose_topic: str | None,
    with_tf: bool,
    every: int,
    image_dir: str | Path | None,
) -> _BagContent:
    rb = _rosbags()
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise InputError(f"every: expected an integer >= 1, got {every!r}")
    every = int(every)
    paths = bag_paths(Path(root))
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (rb.highlevel.AnyReaderError, OSError) as exc:
        raise FormatError(root, None, f"cannot open the bag: {exc}") from None
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        img_topic = _pick_topic(topics, image_topic, (IMAGE, COMPRESSED_IMAGE), "image_topic", root, True)
        cam = parse_camera_option(camera) if camera is not None else None
        info_topic = None
        if cam is None:
            info_topic = _pick_topic(topics, camera_info_topic, (CAMERA_INFO,), "camera_info_topic", root, False)
            if info_topic is None:
                raise FormatError(
                    root, None, "cannot determine the intrinsics: the bag has no sensor_msgs/CameraInfo topic; pass "
                    "the option camera='PINHOLE W H fx fy cx cy' (localize: --camera)"
                )
        if pose_topic is not None:
            _pick_topic(topics, pose_topic, POSE_TYPES, "pose_topic", root, True)
        wanted = {img_topic, info_topic, pose_topic}
        if with_tf:
            wanted |= {t for t, ty in topics.items() if ty == TF_MESSAGE and t in ("/tf", "/tf_static")}
        conns = [c for c in reader.connections if c.topic in wanted]
        out_dir = Path(image_dir) if image_dir is not None else default_image_dir(paths, img_topic)
        slug = img_topic.strip("/").replace("/", "_") or "image"
        pending: list[tuple[str, Path, int, int, str]] = []  # name, file, index, stamp, frame
        pose_times: list[float] = []
        poses: list[Pose] = []
        pose_frame: str | None = None
        tf = _TfBuffer()
        n_image = 0
        names: set[str] = set()
        for conn, bag_ns, raw in reader.messages(connections=conns):
            if conn.topic == img_topic:
                index = n_image
                n_image += 1
                if index % every:
                    continue
            elif conn.topic == info_topic and cam is not None:
                continue
            where = at_stamp(conn.topic, int(bag_ns))
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds for a damaged message
                raise FormatError(root, None, f"{where} (bag time): cannot decode the {conn.msgtype} message "
                                              f"({type(exc).__name__}: {exc})") from None
            ns = _stamp_ns(msg, bag_ns)
            where = at_stamp(conn.topic, ns)
            try:
                if conn.topic == img_topic:
                    name = f"{slug}/{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"
                    while name in names:
                        name += "_"
                    names.add(name)
                    path = _store_image(out_dir, name, msg, conn.msgtype)
                    pending.append((str(path.relative_to(out_dir)), path, index, ns, frame_name(msg.header.frame_id)))
                elif conn.topic == info_topic and cam is None:
                    cam = camera_from_camera_info(msg, rectified_topic(img_topic), _CAMERA_HINT)
                elif conn.topic == pose_topic:
                    p = msg.pose if conn.msgtype == POSE_STAMPED else msg.pose.pose
                    poses.append(pose_from_ros(p.position, p.orientation))
                    pose_times.append(ns * 1e-9)
                    if conn.msgtype == ODOMETRY:
                        pose_frame = frame_name(msg.child_frame_id)
                elif conn.msgtype == TF_MESSAGE:
                    tf.add(msg, conn.topic == "/tf_static", bag_ns)
            except InputError as exc:
                raise FormatError(root, None, f"{where}: {exc}") from None
    finally:
        reader.close()
    if cam is None:
        raise FormatError(root, None, f"{info_topic}: no CameraInfo message in the bag; pass the option camera=...")
    images = [BagImage(name, path, cam, index, ns * 1e-9, frame) for name, path, index, ns, frame in pending]
    if not images:
        raise FormatError(root, None, f"expected messages on {img_topic}, found none")
    try:  # the size from the header: nothing is decoded here (the pixel cap of every image path)
        _fmt, width, height = declared_size(Path(images[0].path).read_bytes())
        check_image_pixels(width, height, f"{images[0].path}")
    except (InputError, OSError) as exc:
        raise FormatError(root, None, f"{at_stamp(img_topic, pending[0][3])}: cannot decode the first image "
                                      f"({images[0].path}): {exc}") from None
    if (width, height) != (images[0].camera.width, images[0].camera.height):
        raise FormatError(
            root, None, f"{img_topic}: images are {width}x{height} but the camera is "
            f"{images[0].camera.width}x{images[0].camera.height}; check camera_info_topic / camera"
        )
    return _BagContent(img_topic, images, pose_times, poses, pose_frame, tf)


def _store_image(out_dir: Path, name: str, msg: Any, msgtype: str) -> Path:
    """Write one image message to ``out_dir`` (once); InputError for a message that is no camera image."""
    if msgtype == COMPRESSED_IMAGE:
        fmt = str(msg.format).lower()
        encoding = fmt.split(";")[0].strip()
        if "compresseddepth" in fmt or _is_depth_encoding(encoding):
            raise InputError(f"compressed depth images ({msg.format!r}) are not camera images; choose the camera's "
                             "image topic with image_topic=TOPIC")
        data = bytes(msg.data)
        try:
            kind, w, h = image_size_from_header(data)
        except ImageFormatError as exc:
            raise InputError(f"the CompressedImage data ({msg.format!r}, {len(data)} bytes) is not a readable JPEG or "
                             f"PNG: {exc}") from None
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
    content = _read_bag(Path(root), image_topic=image_topic, camera_info_topic=camera_info_topic, camera=camera,
                        pose_topic=None, with_tf=False, every=every, image_dir=image_dir)
    _shared_stamps(content.images, content.image_topic, "kept under distinct names (their stamps do not tell them "
                                                         "apart in time)")
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
    base_from_camera = parse_transform(base_to_camera, "base_to_camera") if base_to_camera is not None else None
    content = _read_bag(root, image_topic=image_topic, camera_info_topic=camera_info_topic, camera=camera,
                        pose_topic=pose_topic, with_tf=True, every=every, image_dir=image_dir)
    images = content.images
    ambiguous = _shared_stamps(images, content.image_topic, "skipped: a pose cannot be paired with one of them")
    times = np.array([im.timestamp for im in images])
    if pose_topic is not None:
        if not content.poses:
            raise FormatError(root, None, f"expected pose messages on {pose_topic}, found none")
        pose_times, poses = distinct_samples(content.pose_times, content.poses, pose_topic)
        idx = associate_timestamps(times, pose_times, float(max_dt))
        world_from_posed = [poses[i] if i >= 0 else None for i in idx]
        posed_frame = content.pose_frame
    else:
        world_from_posed = content.tf.poses_at(frame_name(tf_parent), frame_name(tf_child), times, float(max_dt), root)
        posed_frame = frame_name(tf_child)
    extrinsic = base_from_camera
    if extrinsic is None and posed_frame:
        image_frame = images[0].frame_id
        if image_frame and image_frame != posed_frame:
            extrinsic = content.tf.static_chain(posed_frame, image_frame)
            if extrinsic is None:
                logger.warning(
                    "%s: the poses are of frame %r, the images of frame %r, and /tf_static does not link them; "
                    "taking the poses as the camera's (pass base_to_camera='x y z qx qy qz qw' if not)",
                    root, posed_frame, image_frame,
                )
    elif extrinsic is None and images[0].frame_id in content.tf.static:
        logger.warning(
            "%s: %s does not name its posed frame, and /tf_static places the image frame %r below %r; taking "
            "the poses as the camera's (if they are of the base, pass base_to_camera='x y z qx qy qz qw')",
            root, pose_topic, images[0].frame_id, content.tf.static[images[0].frame_id][0],
        )
    out = []
    for k, (im, w_from_p) in enumerate(zip(images, world_from_posed)):
        if w_from_p is None or k in ambiguous:
            continue
        world_from_cam = w_from_p if extrinsic is None else w_from_p @ extrinsic
        out.append(PosedImage(name=im.name, path=im.path, cam_from_world=world_from_cam.inverse(), camera=im.camera,
                              index=im.index, timestamp=im.timestamp))
    skipped = sum(w is None for k, w in enumerate(world_from_posed) if k not in ambiguous)
    source = pose_topic or f"tf {tf_parent} -> {tf_child}"
    if not out:
        raise FormatError(
            root, None, f"expected images with a pose ({source}) within max_dt = {float(max_dt):g} s, found none "
            f"({len(images)} images); check the topics/frames or raise max_dt"
        )
    if skipped:
        logger.warning("%s: %d of %d images have no pose (%s) within max_dt = %g s and are skipped",
                       root, skipped, len(images), source, float(max_dt))
    return out


# ---- writing ----------------------------------------------------------------------------------
STORAGES = ("rosbag1", "sqlite3", "mcap")
POSE_MESSAGES = {"PoseStamped": POSE_STAMPED, "PoseWithCovarianceStamped": POSE_WITH_COVARIANCE,
                 "Odometry": ODOMETRY, "tf": TF_MESSAGE}


def write_rosbag(
    out: Path,
    images: Sequence[PosedImage],
    *,
    storage: str = "sqlite3",
    compressed: bool = False,
    image_topic: str = "/camera/image_raw",
    camera_info_topic: str | None = "/camera/camera_info",
    pose_topic: str = "/pose",
    pose_message: str = "PoseStamped",
    world_frame: str = "map",
    base_frame: str = "base_link",
    camera_frame: str = "camera_optical_frame",
    base_from_camera: Pose | None = None,
    pose_delay: float = 0.0,
) -> Path:
    """Write posed images as a ROS bag (the inverse of :func:`read_rosbag`).

    Args:
        out: a new ``.bag`` file (``storage="rosbag1"``) or a new ROS 2 bag folder.
        images: posed images; stamps are their ``timestamp`` (else ``0.1 s * index``).
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
    _rosbags()
    from rosbags.typesys import Stores, get_typestore

    if storage not in STORAGES:
        raise InputError(f"storage: expected one of {', '.join(STORAGES)}, got {storage!r}")
    if pose_message not in POSE_MESSAGES:
        raise InputError(f"pose_message: expected one of {', '.join(POSE_MESSAGES)}, got {pose_message!r}")
    ros1 = storage == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if TF_MESSAGE not in ts.types:  # the noetic store lacks tf2_msgs
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    T = ts.types
    out = Path(out)
    posed_frame = base_frame if base_from_camera is not None else camera_frame

    def stamp(ns: int) -> Any:
        return T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(ns: int, frame: str, seq: int = 0) -> Any:
        kw = {"seq": seq} if ros1 else {}
        return T["std_msgs/msg/Header"](**kw, stamp=stamp(ns), frame_id=frame)

    def pose_msg(p: Pose) -> Any:
        q, t = p.quat_wxyz, p.t
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))

    def transform_msg(ns: int, parent: str, child: str, p: Pose) -> Any:
        q, t = p.quat_wxyz, p.t
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]),
                                                           w=float(q[0]))))

    writer, serialize = _open_writer(out, storage, ts)
    with writer:
        conns: dict[str, Any] = {}

        def add(topic: str, msgtype: str) -> Any:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            return conns[topic]

        if base_from_camera is not None:
            ns0 = _stamp_of(images[0]) if images else 0
            msg = T[TF_MESSAGE](transforms=[transform_msg(ns0, base_frame, camera_frame, base_from_camera)])
            writer.write(add("/tf_static", TF_MESSAGE), ns0, serialize(msg, TF_MESSAGE))
        for seq, im in enumerate(images):
            ns = _stamp_of(im)
            world_from_cam = im.cam_from_world.inverse()
            world_from_posed = (world_from_cam if base_from_camera is None
                                else world_from_cam @ base_from_camera.inverse())
            pns = ns + int(round(pose_delay * 1e9))
            if pose_message == "tf":
                msg = T[TF_MESSAGE](transforms=[transform_msg(pns, world_frame, posed_frame, world_from_posed)])
                writer.write(add("/tf", TF_MESSAGE), pns, serialize(msg, TF_MESSAGE))
            else:
                mt = POSE_MESSAGES[pose_message]
                p = pose_msg(world_from_posed)
                if mt == POSE_STAMPED:
                    msg = T[mt](header=header(pns, world_frame, seq), pose=p)
                else:
                    cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=np.zeros(36))
                    if mt == POSE_WITH_COVARIANCE:
                        msg = T[mt](header=header(pns, world_frame, seq), pose=cov)
                    else:
                        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
                        twist = T["geometry_msgs/msg/TwistWithCovariance"](
                            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36))
                        msg = T[mt](header=header(pns, world_frame, seq), child_frame_id=posed_frame, pose=cov,
                                    twist=twist)
                writer.write(add(pose_topic, mt), pns, serialize(msg, mt))
            if camera_info_topic is not None:
                msg = _camera_info_msg(T, header(ns, camera_frame, seq), im.camera, ros1)
                writer.write(add(camera_info_topic, CAMERA_INFO), ns, serialize(msg, CAMERA_INFO))
            if compressed:
                data = Path(im.path).read_bytes()
                fmt = "png" if Path(im.path).suffix.lower() == ".png" else "jpeg"
                msg = T[COMPRESSED_IMAGE](header=header(ns, camera_frame, seq), format=fmt,
                                          data=np.frombuffer(data, dtype=np.uint8))
                writer.write(add(image_topic, COMPRESSED_IMAGE), ns, serialize(msg, COMPRESSED_IMAGE))
            else:
                img = cv2.imread(str(im.path), cv2.IMREAD_UNCHANGED)
                if img is None:
                    raise InputError(f"{im.path}: cannot read image")
                if img.ndim == 3 and img.shape[2] == 4:
                    img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
                enc = "mono8" if img.ndim == 2 else "bgr8"
                if img.dtype != np.uint8:
                    raise InputError(f"{im.path}: only 8-bit images can be written as sensor_msgs/Image")
                msg = T[IMAGE](header=header(ns, camera_frame, seq), height=img.shape[0], width=img.shape[1],
                               encoding=enc, is_bigendian=0, step=img.shape[1] * (1 if img.ndim == 2 else 3),
                               data=np.ascontiguousarray(img).reshape(-1))
                writer.write(add(image_topic, IMAGE), ns, serialize(msg, IMAGE))
    return out


def _stamp_of(im: PosedImage) -> int:
    t = im.timestamp if im.timestamp is not None else 0.1 * im.index
    return int(round(float(t) * 1e9))


def _camera_info_msg(T: Any, header: Any, cam: Camera, ros1: bool) -> Any:
    """A rosbags CameraInfo of ``cam`` (:func:`planarloc.io.ros_messages.camera_info_fields`)."""
    info = camera_info_fields(cam)
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    arrays = {(k.upper() if ros1 else k): np.asarray(info[k], dtype=float) for k in ("d", "k", "r", "p")}
    return T[CAMERA_INFO](header=header, height=info["height"], width=info["width"],
                          distortion_model=info["distortion_model"], binning_x=0, binning_y=0, roi=roi, **arrays)


def _open_writer(out: Path, storage: str, ts: Any) -> tuple[Any, Any]:
    if out.exists():
        raise InputError(f"{out}: exists already; a bag is never overwritten")
    if storage == "rosbag1":
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(out), ts.serialize_ros1
    import inspect

    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    kwargs: dict[str, Any] = {}
    params = inspect.signature(Writer2).parameters
    if "version" in params:
        kwargs["version"] = 9
    if "storage_plugin" in params:
        kwargs["storage_plugin"] = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    elif storage == "mcap":
        raise InputError("writing mcap needs rosbags >= 0.10 with the mcap storage plugin")
    return Writer2(out, **kwargs), ts.serialize_cdr
