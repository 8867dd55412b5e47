"""Replay posed images to the ROS 2 node and collect what it publishes (tests, benchmarks, demos).

:func:`replay` is an rclpy node that publishes each frame's image (``sensor_msgs/Image`` mono8, or
``CompressedImage`` PNG) with its ``CameraInfo``, optional ``nav_msgs/Odometry`` and a static
base → camera transform, and records the node's poses, ``map → odom`` transforms and
diagnostics. ``lockstep`` waits for each frame's diagnostic before the next frame (every frame
is localized, whatever the machine's speed); otherwise frames go out at ``rate_hz`` and the node
drops what it cannot keep up with (its diagnostics count them). :class:`NodeProcess` runs
``planarloc ros2`` as a subprocess.
"""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from planarloc.extras import require
from planarloc.features.images import read_gray
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.ros_messages import camera_info_fields
from planarloc.ros2.conversions import pose_from_ros, ros_from_pose, stamp_parts, stamp_seconds
from planarloc.ros2.interfaces import tf_message_type


@dataclass(frozen=True)
class ReplayFrame:
    """One frame to replay: an image, its camera, stamp and optional odometry.

    ``image``: a file or an array (sent as mono8 ``Image``, or as a PNG ``CompressedImage``), or
    ``bytes`` sent as they are as a ``CompressedImage``'s data (e.g. empty or damaged data).
    ``camera``: its ``CameraInfo`` is published before the image; None: no CameraInfo.
    ``odom_from_base``: the odometry's pose of the base at this stamp (None: no Odometry message).
    ``capture_time``: when the camera took it (s, any origin): without lockstep the frame goes out
    that long after the first frame, as a camera delivers it (a stamp may lie about it); None
    for every frame: at ``rate_hz``.
    """

    image: str | Path | np.ndarray | bytes
    camera: Camera | None
    stamp: float
    odom_from_base: Pose | None = None
    capture_time: float | None = None


@dataclass
class ReplayResult:
    """What the node published, keyed by the image stamp (seconds, rounded to the nanosecond)."""

    poses: dict[float, tuple[Pose, np.ndarray, str]] = field(
        default_factory=dict
    )  # parent_from_child, cov, frame
    map_from_odom: dict[float, tuple[Pose, str, str]] = field(default_factory=dict)  # pose, parent, child
    diagnostics: dict[float, dict[str, str]] = field(default_factory=dict)
    published: int = 0
    seconds: float = 0.0


def _key(stamp: object) -> float:
    return round(stamp_seconds(stamp), 9)


def fill_camera_info(msg: object, camera: Camera) -> None:
    """Fill a ``sensor_msgs/CameraInfo`` with the camera's fields (:func:`camera_info_fields`)."""
    for name, value in camera_info_fields(camera).items():
        setattr(msg, name, value)


@dataclass(frozen=True)
class ReplaySettings:
    """Topics, frames and pacing of :func:`replay` (see its docstring)."""

    camera_frame: str = "camera_optical"
    base_frame: str = "base_link"
    odom_frame: str = "odom"
    base_from_camera: Pose | None = None
    image_topic: str = "/camera/image_raw"
    camera_info_topic: str = "/camera/camera_info"
    odom_topic: str = "/odom"
    pose_topic: str = "/planarloc/pose"
    diagnostics_topic: str = "/diagnostics"
    lockstep: bool = True
    rate_hz: float = 10.0
    wait_s: float = 120.0
    settle_s: float = 2.0
    initialpose_before: int | None = None

    @property
    def compressed(self) -> bool:
        return self.image_topic.rstrip("/").endswith("/compressed")


class _Replayer:
    """The replay's rclpy node: its publishers, the subscriptions that fill ``result``,
    and one stage per step."""

    def __init__(self, rclpy: Any, s: ReplaySettings):
        self.rclpy, self.s, self.result = rclpy, s, ReplayResult()
        self.TFMessage = tf_message_type()
        self.node = rclpy.create_node("planarloc_replay")

    def create_endpoints(self) -> None:
        """The publishers, and the subscriptions that fill ``result``."""
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        node, s = self.node, self.s
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.image_pub = node.create_publisher(
            CompressedImage if s.compressed else Image, s.image_topic, reliable
        )
        self.info_pub = node.create_publisher(CameraInfo, s.camera_info_topic, reliable)
        self.odom_pub = node.create_publisher(Odometry, s.odom_topic, reliable)
        self.initial_pub = node.create_publisher(PoseWithCovarianceStamped, "/initialpose", reliable)
        self.static_pub = node.create_publisher(
            self.TFMessage,
            "/tf_static",
            QoSProfile(
                depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE
            ),
        )
        node.create_subscription(PoseWithCovarianceStamped, s.pose_topic, self._on_pose, reliable)
        node.create_subscription(self.TFMessage, "/tf", self._on_tf, QoSProfile(depth=100))
        node.create_subscription(DiagnosticArray, s.diagnostics_topic, self._on_diagnostics, reliable)

    def _on_pose(self, msg: Any) -> None:
        p = msg.pose.pose
        self.result.poses[_key(msg.header.stamp)] = (
            pose_from_ros(p.position, p.orientation),
            np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6),
            msg.header.frame_id,
        )

    def _on_tf(self, msg: Any) -> None:
        for tf in msg.transforms:
            self.result.map_from_odom[_key(tf.header.stamp)] = (
                pose_from_ros(tf.transform.translation, tf.transform.rotation),
                tf.header.frame_id,
                tf.child_frame_id,
            )

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            self.result.diagnostics[_key(msg.header.stamp)] = {kv.key: kv.value for kv in status.values}

    def spin(self, times: int, timeout_s: float) -> None:
        for _ in range(times):
            self.rclpy.spin_once(self.node, timeout_sec=timeout_s)

    def connect(self) -> None:
        """Wait for the planarloc node, then publish the static base → camera transform."""
        from geometry_msgs.msg import TransformStamped

        s = self.s
        deadline = time.monotonic() + s.wait_s
        while (
            self.image_pub.get_subscription_count() == 0
            or self.node.count_publishers(s.diagnostics_topic) == 0
        ):
            if time.monotonic() > deadline:
                raise InputError(f"no planarloc node subscribes to {s.image_topic} within {s.wait_s:.0f} s")
            self.rclpy.spin_once(self.node, timeout_sec=0.1)
        if s.base_from_camera is not None:
            tf = TransformStamped()
            tf.header.frame_id, tf.child_frame_id = s.base_frame, s.camera_frame
            t, q = ros_from_pose(s.base_from_camera)
            tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = t
            r = tf.transform.rotation
            r.x, r.y, r.z, r.w = q
            self.static_pub.publish(self.TFMessage(transforms=[tf]))
        self.spin(10, 0.05)  # let the subscriptions of both sides match

    def publish_initial_pose(self, sec: int, nanosec: int) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped

        initial = PoseWithCovarianceStamped()
        initial.header.frame_id = "map"
        initial.header.stamp.sec, initial.header.stamp.nanosec = sec, nanosec
        initial.pose.pose.orientation.w = 1.0
        self.initial_pub.publish(initial)
        self.spin(10, 0.02)

    def publish_side_messages(self, frame: ReplayFrame, sec: int, nanosec: int) -> None:
        """The frame's Odometry and CameraInfo (those it has)."""
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import CameraInfo

        if frame.odom_from_base is not None:
            odom = Odometry()
            odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
            odom.header.frame_id, odom.child_frame_id = self.s.odom_frame, self.s.base_frame
            t, q = ros_from_pose(frame.odom_from_base)
            odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z = t
            o = odom.pose.pose.orientation
            o.x, o.y, o.z, o.w = q
            self.odom_pub.publish(odom)
        if frame.camera is not None:
            info = CameraInfo()
            info.header.stamp.sec, info.header.stamp.nanosec = sec, nanosec
            info.header.frame_id = self.s.camera_frame
            fill_camera_info(info, frame.camera)
            self.info_pub.publish(info)

    def image_message(self, i: int, frame: ReplayFrame, sec: int, nanosec: int) -> Any:
        from sensor_msgs.msg import CompressedImage, Image

        if isinstance(frame.image, bytes):
            if not self.s.compressed:
                raise InputError(
                    f"frame {i}: bytes are sent as a CompressedImage; use a /compressed image_topic"
                )
            msg = CompressedImage(format="png", data=frame.image)
        elif self.s.compressed:
            gray = frame.image if isinstance(frame.image, np.ndarray) else read_gray(frame.image)
            msg = CompressedImage(format="png", data=cv2.imencode(".png", gray)[1].tobytes())
        else:
            gray = frame.image if isinstance(frame.image, np.ndarray) else read_gray(frame.image)
            msg = Image(
                height=gray.shape[0],
                width=gray.shape[1],
                encoding="mono8",
                step=gray.shape[1],
                data=np.ascontiguousarray(gray).tobytes(),
            )
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.header.frame_id = self.s.camera_frame
        return msg

    def wait_for_diagnostic(self, i: int, frame: ReplayFrame) -> None:
        key, wait_s = round(frame.stamp, 9), self.s.wait_s
        deadline = time.monotonic() + wait_s
        while key not in self.result.diagnostics:
            if time.monotonic() > deadline:
                raise InputError(f"frame {i} (stamp {frame.stamp:.3f}): no diagnostic within {wait_s:.0f} s")
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def wait_until(self, next_at: float) -> None:
        while time.perf_counter() < next_at:
            self.rclpy.spin_once(self.node, timeout_sec=max(0.0, min(0.01, next_at - time.perf_counter())))

    def run(self, frames: Sequence[ReplayFrame]) -> ReplayResult:
        s, t0 = self.s, None
        self.create_endpoints()
        self.connect()
        for i, frame in enumerate(frames):
            sec, nanosec = stamp_parts(frame.stamp)
            if i == s.initialpose_before:
                self.publish_initial_pose(sec, nanosec)
            self.publish_side_messages(frame, sec, nanosec)
            msg = self.image_message(i, frame, sec, nanosec)
            if i == 0:  # the CameraInfo must be there before the first image
                self.spin(5, 0.02)
                t0 = time.perf_counter()  # the clock of the rate starts at the first image
            self.image_pub.publish(msg)
            if s.lockstep:
                self.wait_for_diagnostic(i, frame)
            else:
                assert t0 is not None  # set at the first frame
                first = frames[0].capture_time
                later = frames[i + 1].capture_time if i + 1 < len(frames) else None
                self.wait_until(
                    t0 + (later - first if later is not None and first is not None else (i + 1) / s.rate_hz)
                )
        self.result.seconds = time.perf_counter() - t0 if t0 is not None else 0.0
        end = time.monotonic() + s.settle_s
        while time.monotonic() < end:  # the last answers (poses after their diagnostics, trailing frames)
            self.rclpy.spin_once(self.node, timeout_sec=0.05)
        self.result.published = len(self.result.poses)
        return self.result


def replay(
    frames: Sequence[ReplayFrame], settings: ReplaySettings | None = None, **overrides: Any
) -> ReplayResult:
    """Publish ``frames`` in order to a running ``planarloc ros2`` and collect its answers.

    ``settings`` (None: defaults), with keyword ``overrides`` of any :class:`ReplaySettings` field,
    e.g. ``replay(frames, base_from_camera=pose, lockstep=False)``:

    - ``*_frame``, ``*_topic``: the TF frames and topics used; ``base_from_camera`` is published
      as a static transform (None: none).
    - ``image_topic`` ending in ``/compressed`` sends PNG ``CompressedImage`` messages (a frame's
      ``bytes`` as they are).
    - ``lockstep``: wait for each frame's diagnostic; otherwise frames go out at ``rate_hz`` (or
      at their ``capture_time``).
    - ``wait_s``: how long to wait for the node's subscription (and, in lockstep, for each
      frame's diagnostic); ``settle_s``: how long to collect answers after the last frame.
    - ``initialpose_before``: publish an identity pose on ``/initialpose`` before that frame, as
      rviz's "2D Pose Estimate" does (the node restarts its stream).

    Raises:
        InputError: no node subscribes to ``image_topic`` within ``wait_s``, or (lockstep) a
            frame got no diagnostic within ``wait_s``.
    """
    settings = replace(settings or ReplaySettings(), **overrides)
    rclpy = require("rclpy", "ros2")
    own_context = not rclpy.ok()
    if own_context:
        rclpy.init(args=["planarloc_replay"])
    replayer = _Replayer(rclpy, settings)
    try:
        return replayer.run(frames)
    finally:
        replayer.node.destroy_node()
        if own_context:
            rclpy.try_shutdown()


@contextlib.contextmanager
def exclusive_domain() -> Iterator[int]:
    """A ROS domain (1..101) that no other user of this function on the machine holds (a test, a
    benchmark): a lock file per domain in the temp folder, taken over when its process is gone."""
    lock_dir = Path(tempfile.gettempdir()) / "planarloc-ros-domains"
    lock_dir.mkdir(exist_ok=True)
    for domain in random.Random(os.getpid() + time.monotonic_ns()).sample(range(1, 102), 101):
        lock = lock_dir / f"{domain}.lock"
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                os.kill(int(lock.read_text() or 0), 0)
                continue  # held by a live process
            except (ProcessLookupError, ValueError):
                lock.unlink(missing_ok=True)  # stale: its process is gone
                continue
            except PermissionError:
                continue
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        try:
            yield domain
        finally:
            lock.unlink(missing_ok=True)
        return
    raise RuntimeError("every ROS domain 1..101 is held by another process")


def loopback_env(domain: int) -> dict[str, str]:
    """The environment of a ROS 2 process that discovers peers on this machine only, on ``domain``
    (Fast DDS), so that parallel runs on one machine never meet."""
    return {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    }


def planarloc_command() -> list[str]:
    """The ``planarloc`` console script of this Python (``python -m planarloc.cli.main`` without one)."""
    exe = Path(sys.executable).with_name("planarloc")
    return (
        [str(exe)]
        if exe.exists()
        else [shutil.which("planarloc") or sys.executable, "-m", "planarloc.cli.main"]
    )


class NodeProcess:
    """``planarloc ros2 ARGS`` running as a subprocess with ``env`` added; its output is collected."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(
            [*planarloc_command(), "ros2", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **env},
        )
        self.stderr: list[str] = []
        self.stdout: list[str] = []
        self._threads = [
            threading.Thread(target=self._read, args=(s, out), daemon=True)
            for s, out in ((self.proc.stderr, self.stderr), (self.proc.stdout, self.stdout))
        ]
        for t in self._threads:
            t.start()

    @staticmethod
    def _read(stream: Any, out: list[str]) -> None:
        for line in stream:
            out.append(line)

    def wait_ready(self, timeout: float = 240.0) -> None:
        """Wait for the node's banner (its map is open and it subscribes).

        Raises:
            RuntimeError: the node exited or did not start within ``timeout``.
        """
        end = time.monotonic() + timeout
        while not any("planarloc ros2: localizing" in line for line in self.stderr):
            if self.proc.poll() is not None:
                time.sleep(0.2)
                raise RuntimeError(f"the node exited with {self.proc.returncode}: {''.join(self.stderr)}")
            if time.monotonic() > end:
                raise RuntimeError(f"the node did not start within {timeout} s: {''.join(self.stderr)}")
            time.sleep(0.1)

    def interrupt(self, timeout: float = 60.0) -> int:
        """Ctrl-C: send SIGINT and return the exit code.

        Raises:
            RuntimeError: the node did not exit within ``timeout`` (it is killed; the message has
                the end of its stderr).
        """
        self.proc.send_signal(signal.SIGINT)
        try:
            rc = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise RuntimeError(
                f"the node did not exit within {timeout:.0f} s of SIGINT: {''.join(self.stderr)[-2000:]}"
            ) from None
        for t in self._threads:
            t.join(timeout=5)
        return rc

    def kill(self) -> None:
        """SIGKILL, if still running."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)
