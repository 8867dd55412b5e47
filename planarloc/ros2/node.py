"""The ROS 2 node of ``planarloc ros2``: camera frames in, map poses, ``map → odom`` and diagnostics out.

Topics (names are parameters, see :class:`~planarloc.ros2.settings.NodeSettings`):

- in: ``sensor_msgs/Image`` on ``image_topic`` (``sensor_msgs/CompressedImage`` when the name
  ends in ``/compressed``) with ``sensor_msgs/CameraInfo`` on ``camera_info_topic`` (until one
  arrives, the map's camera when the map has only one, with a warning once); optional
  ``nav_msgs/Odometry`` (``odom_topic``), ``/tf`` and ``/tf_static`` (base → camera) and
  ``geometry_msgs/PoseWithCovarianceStamped`` on ``initialpose_topic``.
- out: ``geometry_msgs/PoseWithCovarianceStamped`` on ``pose_topic`` in ``map_frame``, stamped with
  the image's stamp: the pose of ``base_frame`` when base → camera is known (TF or the
  ``base_to_camera`` parameter), else of the image's frame; the ``map_frame → odom_frame``
  transform on ``/tf`` when odometry is given and ``tf_broadcast`` is true (AMCL's contract:
  ``map_from_odom = map_from_base · odom_from_base⁻¹`` at the image's stamp, the transform stamped
  ``transform_tolerance_s`` later); ``diagnostic_msgs/DiagnosticArray`` on ``diagnostics_topic``
  for every frame.

The map frame (``map_frame_convention``): ``z_up`` (default) publishes in a z-up, gravity-aligned
``map`` (REP-103/105): ``map_from_world = map_from_world_from_gravity(g_world)``
(:mod:`planarloc.ros2.conversions`), a rotation about the world's origin computed once from the
map's stored gravity (declared by the dataset format, given with ``up=``, or estimated from the
map's camera centres; ``planarloc map info``). Its z axis is the world's up (``−g_world``), its x
axis the world's x projected into the ground plane, y = z × x. So ``map_from_base =
map_from_world · world_from_base`` and the ROS covariance (position, rotation vector about the
parent's axes) is rotated by ``blockdiag(R, R)``; ``map → odom`` is computed from the z-up pose.
For KITTI and the generated worlds (x right, y down, z forward of the first camera): map x =
world x, map y = world z, map z = −world y. ``world`` publishes in the map's world itself.

What is published (the node is never confidently wrong): a frame the stream calls
``localized`` (an absolute fix accepted in this frame), and with ``publish_predicted`` a
``predicted`` one, each only when its position std is at most ``max_published_std_m``. A
``lost`` frame publishes only its diagnostic. ``map → odom`` is re-sent with each localized or
predicted frame's stamp (as AMCL re-sends its last transform) and never after ``lost``.

Bad frames (an empty or undecodable image, a uniform one such as a black frame, a frame of the
wrong size for its camera) never stop the node: each is a ``failed`` diagnostic with its
``reason`` and the node goes on with the next frame; the stream keeps its state (a bad frame is
treated like a dropped one). Only an unexpected exception (a bug) is logged with its traceback.

Frames: the image callback queues the frame; a worker thread localizes the queued frames in
order. The queue holds at most ``queue_size`` frames: when the worker falls further behind (a
slow first fix, a machine too slow for the camera), the oldest waiting frame is dropped and
counted (``frames_dropped``), so that a frame never waits behind more than ``queue_size - 1``
others. A short queue poses every frame through a one-off slow step (the tracking path catches
up in a few frames) where a single slot would drop them, and a dropped frame also costs the
next one (tracking across a gap is harder). ``/initialpose`` restarts the stream: the window is forgotten and
the next pose comes from a global fix (planarloc localizes absolutely; the given pose is not
used as a prior).

Start-up on an empty kernel cache (no ``planarloc warmup``): the kernels run as Python while a
detached process compiles them (:mod:`planarloc.compile.first_use`; a warning once), so the node
is up in seconds and its first frames are slower; ``PLANARLOC_COMPILE=wait`` compiles them on
every core before the node subscribes.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import cv2
import numpy as np

from planarloc.compile import steps_for
from planarloc.compile.first_use import FirstUse, compile_setting, first_use_or_compile
from planarloc.extras import require
from planarloc.features import learned
from planarloc.features.registry import check_map_feature_kind
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io import strict_json
from planarloc.localize.localizer import Localizer
from planarloc.localize.records import error_record, frame_record
from planarloc.localize.sequence import FrameStatus, SequenceEstimate, SequenceLocalizer
from planarloc.ros2.conversions import (
    OdometryBuffer,
    TransformTree,
    camera_from_camera_info,
    map_from_odom,
    map_from_world_from_gravity,
    map_pose_of_child,
    pose_from_ros,
    ros_from_pose,
    stamp_parts,
    stamp_seconds,
    transform_edge,
)
from planarloc.ros2.frame_inputs import NO_CAMERA_INFO, frame_camera, frame_pixels
from planarloc.ros2.frame_queue import FrameCounts, FrameQueue
from planarloc.ros2.interfaces import tf_message_type
from planarloc.ros2.settings import (  # noqa: F401  (NodeSettings, PARAMETERS: the node's public names)
    NODE_NAME,
    PARAMETERS,
    NodeSettings,
    check_parameter_names,
    parameter_help,
)

logger = logging.getLogger(__name__)


class LocalizerNode:
    """The rclpy node: subscriptions, a worker thread around a :class:`SequenceLocalizer`, publishers.

    Args:
        node: an rclpy ``Node`` whose parameters are declared by :func:`declare_settings`.
        settings: the node's settings.
    """

    def __init__(self, node: Any, settings: NodeSettings) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        self.node, self.settings = node, settings
        self.TFMessage = tf_message_type()
        self.sequence: SequenceLocalizer | None = None
        self.tf = TransformTree()
        self.odometry = OdometryBuffer()
        self.counts = FrameCounts()
        self._base_from_camera_param = settings.base_from_camera
        self._camera: Any = None
        self._camera_error = NO_CAMERA_INFO  # empty once a usable CameraInfo arrived
        self.map_from_world = Pose.identity()  # set by _open (map_frame_convention)
        self.map_frame_note = ""
        self._pending = FrameQueue(settings.queue_size)
        self._map_from_odom: Pose | None = None
        self._last_stamp: float | None = None
        self._cond = threading.Condition()
        self._stop = False
        self._warned: set[str] = set()

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        image_qos = qos_profile_sensor_data if settings.image_qos == "sensor_data" else reliable
        node.create_subscription(
            CompressedImage if settings.compressed else Image, settings.image_topic, self._on_image, image_qos
        )
        node.create_subscription(
            CameraInfo, settings.camera_info_topic, self._on_camera_info, qos_profile_sensor_data
        )
        if settings.odom_topic:
            node.create_subscription(
                Odometry,
                settings.odom_topic,
                self._on_odometry,
                QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT),
            )
        node.create_subscription(
            PoseWithCovarianceStamped, settings.initialpose_topic, self._on_initialpose, reliable
        )
        node.create_subscription(self.TFMessage, "/tf", self._on_tf, QoSProfile(depth=100))
        node.create_subscription(
            self.TFMessage,
            "/tf_static",
            self._on_tf,
            QoSProfile(
                depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE
            ),
        )
        self.pose_pub = node.create_publisher(PoseWithCovarianceStamped, settings.pose_topic, reliable)
        self.tf_pub = (
            node.create_publisher(self.TFMessage, "/tf", QoSProfile(depth=100))
            if settings.tf_broadcast
            else None
        )
        self.diag_pub = node.create_publisher(DiagnosticArray, settings.diagnostics_topic, reliable)
        # The map (SQLite) is opened by the thread that localizes; its errors are raised here.
        self._opened = threading.Event()
        self._open_error: BaseException | None = None
        self._first_use: FirstUse | None = None  # kernels as Python while they compile (_compile)
        self._worker = threading.Thread(target=self._work, name="planarloc-localize", daemon=True)
        self._worker.start()
        self._opened.wait()
        if self._open_error is not None:
            self._worker.join()
            raise self._open_error

    def _open(self) -> None:
        """Open the map and warm the localizer up (in the worker: SQLite stays in one thread)."""
        s = self.settings
        localizer = Localizer(s.map, s.localizer_config())
        check_map_feature_kind(s.map, localizer.features.kind, s.features or None, "parameter features")
        learned.load_backend(
            localizer.features.kind
        )  # a learned map's models (torch) now, not at the first frame
        self.sequence = SequenceLocalizer(localizer, s.sequence_config())
        # The first query of a process is ~10x slower than the next (kernels loaded from the compile
        # cache, first calls into OpenCV): pay for it before the first frame, not with dropped frames.
        gravity = self.sequence.localizer.gravity
        if s.map_frame_convention == "z_up":
            self.map_from_world = map_from_world_from_gravity(gravity.g_world)
            g = ", ".join(f"{v:+.3f}" for v in gravity.g_world)
            self.map_frame_note = (
                f"z-up (REP-103), rotated from the map's world by its gravity ({g}, "
                f"{gravity.source}{': ' + gravity.detail if gravity.detail else ''})"
            )
        else:
            self.map_frame_note = "the map's world (map_frame_convention world)"
        self._first_use = first_use_or_compile(
            steps_for([localizer.config]), self._warn_once, wait=compile_setting() == "wait"
        )
        logger.info("warming up the localizer on the map's own images")
        logger.info("warm-up done in %.1f s", self.sequence.warm_up())

    # ---- callbacks (executor thread: cheap) -------------------------------------------------
    def _on_image(self, msg: Any) -> None:
        with self._cond:
            self.counts.received += 1
            self.counts.dropped += self._pending.push(msg, time.perf_counter())
            self._cond.notify_all()

    def _on_camera_info(self, msg: Any) -> None:
        try:
            camera = camera_from_camera_info(msg, rectified=self.settings.rectified)
        except (InputError, ValueError) as exc:
            self._camera, self._camera_error = None, f"CameraInfo on {self.settings.camera_info_topic}: {exc}"
            self._warn_once(self._camera_error)
            return
        self._camera, self._camera_error = camera, ""

    def _on_odometry(self, msg: Any) -> None:
        try:
            pose = pose_from_ros(msg.pose.pose.position, msg.pose.pose.orientation)
        except InputError as exc:
            self._warn_once(f"odometry: {exc}")
            return
        with self._cond:
            self.odometry.add(
                stamp_seconds(msg.header.stamp),
                pose,
                msg.header.frame_id.lstrip("/"),
                msg.child_frame_id.lstrip("/"),
            )
            self._cond.notify_all()  # a frame may wait for the odometry at its stamp

    def _on_initialpose(self, msg: Any) -> None:
        with self._cond:
            self._pending.restart()
        logger.info("initial pose received: the stream restarts from a global fix")

    def _on_tf(self, msg: Any) -> None:
        edges = []
        for tf in msg.transforms:
            try:
                parent, child, pose = transform_edge(tf)
            except InputError as exc:
                self._warn_once(f"/tf: {exc}")
                continue
            if (parent, child) != (
                self.settings.map_frame,
                self.settings.odom_frame,
            ):  # not our own map -> odom
                edges.append((parent, child, pose))
        with self._cond:
            self.tf.add_many(edges)

    def _warn_once(self, text: str) -> None:
        """A warning on the console and ``/rosout`` (rclpy's logger), once per text."""
        if text not in self._warned:
            self._warned.add(text)
            self.node.get_logger().warning(text)

    # ---- the worker --------------------------------------------------------------------------
    def _work(self) -> None:
        try:
            self._open()
        except BaseException as exc:  # raised again by __init__ in the caller's thread
            self._open_error = exc
            return
        finally:
            self._opened.set()
        while True:
            with self._cond:
                while not self._pending and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                msg, received, reset = self._pending.pop()
            try:
                self._process(msg, received, reset)
                if self._first_use is not None and self._first_use.poll():
                    logger.info("planarloc's kernels are compiled: the next frames run compiled")
            except (
                Exception
            ) as exc:  # a bug must not stop the node silently: log it, count and report the frame
                logger.exception("frame at %.3f failed", stamp_seconds(msg.header.stamp))
                self._fail(msg, f"internal error: {type(exc).__name__}: {exc}", received)

    def stop(self) -> None:
        """Stop the worker after the frame it is localizing."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._worker.join(timeout=30)
        if self._first_use is not None:
            self._first_use.end()

    def _frame_from_camera(self, frame: str, camera_frame: str) -> Pose | None:
        """``frame_from_camera`` (identity for the camera's own frame): TF, else ``base_to_camera``
        for the base frame."""
        if frame.lstrip("/") == camera_frame:
            return Pose.identity()
        with self._cond:
            pose = self.tf.lookup(frame, camera_frame)
        if pose is None and frame.lstrip("/") == self.settings.base_frame:
            pose = self._base_from_camera_param
        return pose

    def _fail(self, msg: Any, reason: str, received: float, camera_source: str = "") -> None:
        """A frame that cannot be localized: counted, and a ``failed`` diagnostic with its reason."""
        self.counts.failed += 1
        self._diagnose(msg.header.stamp, "failed", reason, received, camera_source=camera_source)

    def _camera_for_frame(self) -> tuple[Camera | None, str, str]:
        camera, source, error, warning = frame_camera(
            self._camera,
            self._camera_error,
            self.sequence.localizer.map_cameras,  # type: ignore[union-attr]
            self.settings.camera_info_topic,
        )
        if warning:
            self._warn_once(warning)
        return camera, source, error

    def _process(self, msg: Any, received: float, reset: bool = False) -> None:
        stamp = stamp_seconds(msg.header.stamp)
        camera_frame = (self.settings.camera_frame or msg.header.frame_id).lstrip("/")
        camera, camera_source, error = self._camera_for_frame()
        if error:
            self._fail(msg, error, received)
            return
        try:
            image = frame_pixels(msg, self.settings.compressed)
        except (InputError, ValueError, cv2.error) as exc:  # the data's fault: cv2.error from decoding
            self._fail(msg, f"bad frame: {' '.join(str(exc).split())}", received, camera_source)
            return
        notes = []
        if reset:
            notes.append("restarted by the initial pose")
        elif self._last_stamp is not None and stamp < self._last_stamp:  # a bag played again, a clock reset
            notes.append(f"time went back from {self._last_stamp:.3f} s: the stream restarts")
            logger.warning("%s", notes[-1])
        if notes:
            self.sequence.reset()  # type: ignore[union-attr]
            self._map_from_odom = None
        self._last_stamp = stamp
        # Odometry at the image's stamp, as cam_from_odom for the stream.
        odom_from_child, child_from_camera = None, None
        if self.settings.odom_topic:
            with self._cond:
                # Odometry flowing but not yet at the image's stamp (topics arrive in any order):
                # wait for it up to odom_tolerance_s, so that it is interpolated, not stale.
                deadline = time.monotonic() + self.settings.odom_tolerance_s
                while self.odometry.stamps and self.odometry.stamps[-1] < stamp and not self._stop:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(timeout=left)
                odom_from_child = self.odometry.at(stamp, self.settings.odom_tolerance_s)
                child = self.odometry.child_frame
            if odom_from_child is not None:
                child_from_camera = self._frame_from_camera(child or camera_frame, camera_frame)
                if child_from_camera is None:
                    notes.append(f"odometry ignored: no transform {child} -> {camera_frame}")
                    odom_from_child = None
            elif self.odometry.stamps:
                notes.append("no odometry at the image's stamp")
        odometry = (
            None
            if odom_from_child is None or child_from_camera is None
            else (odom_from_child @ child_from_camera).inverse()
        )
        try:
            est = self.sequence.step(image, camera, stamp, odometry=odometry)  # type: ignore[union-attr]
        except InputError as exc:  # the frame's (e.g. not the size of its camera), not the node's
            self._fail(msg, f"bad frame: {exc}", received, camera_source)
            return
        self.counts.processed += 1
        status = est.status
        setattr(self.counts, status, getattr(self.counts, status) + 1)
        published = self._publish(msg.header.stamp, est, camera_frame, odom_from_child, child_from_camera)
        self._diagnose(msg.header.stamp, status, "; ".join(notes), received, est, published, camera_source)

    def _publishable(self, est: SequenceEstimate) -> bool:
        if est.pose is None or not est.position_std_m <= self.settings.max_published_std_m:
            return False
        return est.status == FrameStatus.LOCALIZED.value or (
            est.status == FrameStatus.PREDICTED.value and self.settings.publish_predicted
        )

    def _publish(
        self,
        stamp: Any,
        est: SequenceEstimate,
        camera_frame: str,
        odom_from_child: Pose | None,
        child_from_camera: Pose | None,
    ) -> bool:
        from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped

        if est.status == FrameStatus.LOST.value:
            self._map_from_odom = None
        if not self._publishable(est):
            return False
        world_from_camera = est.pose.inverse()  # type: ignore[union-attr]
        cov = np.asarray(
            est.covariance, dtype=float
        )  # (6, 6), ROS order already (SequenceEstimate.covariance)
        if not np.isfinite(cov).all():
            return False  # no promise without a finite covariance
        base_from_camera = self._frame_from_camera(self.settings.base_frame, camera_frame)
        if base_from_camera is None:
            self._warn_once(
                f"no transform {self.settings.base_frame} -> {camera_frame}: publishing the pose of "
                f"{camera_frame}"
            )
        camera_from_child = Pose.identity() if base_from_camera is None else base_from_camera.inverse()
        pose, cov = map_pose_of_child(world_from_camera, cov, camera_from_child, self.map_from_world)
        out = PoseWithCovarianceStamped()
        out.header.stamp, out.header.frame_id = stamp, self.settings.map_frame
        (out.pose.pose.position.x, out.pose.pose.position.y, out.pose.pose.position.z), q = ros_from_pose(
            pose
        )
        o = out.pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        out.pose.covariance = [float(v) for v in cov.ravel()]
        self.pose_pub.publish(out)
        self.counts.published += 1
        if odom_from_child is not None and child_from_camera is not None:
            map_from_child = self.map_from_world @ world_from_camera @ child_from_camera.inverse()
            self._map_from_odom = map_from_odom(map_from_child, odom_from_child)
        if self._map_from_odom is not None and self.tf_pub is not None:
            tf = TransformStamped()
            sec, nanosec = stamp_parts(stamp_seconds(stamp) + self.settings.transform_tolerance_s)
            tf.header.stamp.sec, tf.header.stamp.nanosec = sec, nanosec
            tf.header.frame_id, tf.child_frame_id = self.settings.map_frame, self.settings.odom_frame
            t, q = ros_from_pose(self._map_from_odom)
            tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = t
            r = tf.transform.rotation
            r.x, r.y, r.z, r.w = q
            self.tf_pub.publish(self.TFMessage(transforms=[tf]))
        return True

    def _diagnose(
        self,
        stamp: Any,
        status: str,
        note: str,
        received: float,
        est: SequenceEstimate | None = None,
        published: bool = False,
        camera_source: str = "",
    ) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        level = {"localized": DiagnosticStatus.OK, "predicted": DiagnosticStatus.WARN}.get(
            status, DiagnosticStatus.ERROR
        )
        c = self.counts
        values = {
            "status": status,
            "published": str(published).lower(),
            "stamp": f"{stamp_seconds(stamp):.9f}",
            "frames_received": c.received,
            "frames_processed": c.processed,
            "frames_dropped": c.dropped,
            "frames_failed": c.failed,
            "frames_localized": c.localized,
            "frames_predicted": c.predicted,
            "frames_lost": c.lost,
            "poses_published": c.published,
            "fix_rate": f"{c.fix_rate:.4f}",
            "latency_ms": f"{1000 * (time.perf_counter() - received):.1f}",
        }
        if est is not None:
            values.update(
                fix_status=est.fix_status,
                motion_source=est.motion_source,
                position_std_m=f"{est.position_std_m:.4g}",
                rotation_std_deg=f"{est.rotation_std_deg:.4g}",
            )
        if camera_source:
            values["camera_source"] = camera_source  # camera_info, or map (no CameraInfo received)
        if note:
            values["reason" if status == "failed" else "note"] = note
        # The frame's record (docs/schema/record.schema.json), as `localize --sequence` and the
        # service's sessions write it: one schema for every front door.
        name = f"{self.settings.image_topic}@{stamp_seconds(stamp):.9f}"
        record = (
            frame_record(name, est)
            if est is not None
            else error_record(name, note or status, kind="frame", stamp=stamp_seconds(stamp))
        )
        values["record"] = strict_json.dumps(record)
        d = DiagnosticStatus(
            level=level,
            name=f"{NODE_NAME}: localization",
            hardware_id=self.settings.map,
            message=f"{status}{': ' + note if note else ''}",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )
        out = DiagnosticArray(status=[d])
        out.header.stamp = stamp
        self.diag_pub.publish(out)


def declare_settings(
    node: Any, defaults: NodeSettings | dict | None = None, overrides: dict[str, object] | None = None
) -> NodeSettings:
    """Declare every :class:`NodeSettings` field as a ROS parameter (its meaning as the description)
    and read the settings back.

    Precedence, lowest first: ``defaults`` (a NodeSettings or some fields; else NodeSettings'),
    ``--ros-args`` (``--params-file`` and ``-p``, as ROS applies them), ``overrides`` (e.g.
    ``{"map": path}`` from ``--map``; set on the node too, so ``ros2 param get`` shows them).

    Raises:
        InputError: a value of the wrong type or outside its choices, naming the parameter.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.parameter import Parameter

    if isinstance(defaults, NodeSettings):
        defaults = {f.name: getattr(defaults, f.name) for f in fields(defaults)}
    base, overrides, meaning = defaults or {}, overrides or {}, parameter_help()
    values: dict[str, Any] = {}
    for f in fields(NodeSettings):
        default = base.get(f.name, f.default)
        # Typed by the default, but `-p odom_tolerance_s:=1` (an integer) is a fine number of seconds.
        descriptor = ParameterDescriptor(description=meaning[f.name], dynamic_typing=True)
        value: Any = node.declare_parameter(f.name, default, descriptor).value
        if f.name in overrides:
            value = overrides[f.name]
            node.set_parameters([Parameter(f.name, value=value)])
        values[f.name] = _coerce(f.name, value, type(f.default))
    return NodeSettings(**values)


def _coerce(name: str, value: object, kind: type) -> object:
    """``value`` of a ROS parameter as the setting's type (int -> float; no other conversion)."""
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, kind) and not (kind is int and isinstance(value, bool)):
        return value
    expected = {str: "a string", int: "an integer", float: "a number", bool: "true or false"}[kind]
    raise InputError(f"parameter {name}: expected {expected}, got {value!r}")


def run(map_path: str | None, ros_args: Sequence[str]) -> int:
    """``planarloc ros2``: run the node until SIGINT or SIGTERM (exit 0)."""
    rclpy = require("rclpy", "ros2")
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    check_parameter_names(ros_args)
    try:
        rclpy.init(args=[NODE_NAME, "--ros-args", *ros_args] if ros_args else [NODE_NAME])
    except Exception as exc:  # rclpy's RCLError for malformed --ros-args
        raise InputError(f"--ros-args: {' '.join(str(exc).split()[:30])}") from None
    node = worker = None
    try:
        node = rclpy.create_node(NODE_NAME)
        settings = declare_settings(node, overrides={"map": map_path} if map_path else None)
        worker = LocalizerNode(node, settings)
        print(
            f"planarloc ros2: localizing {settings.image_topic} against {settings.map}; poses on "
            f"{settings.pose_topic} in {settings.map_frame}: {worker.map_frame_note} (Ctrl-C stops)",
            file=sys.stderr,
            flush=True,
        )
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            executor.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        c = worker.counts
        print(
            f"planarloc ros2: stopped after {c.received} frames: {c.localized} localized, {c.predicted} "
            f"predicted, {c.lost} lost, {c.dropped} dropped, {c.failed} failed; "
            f"{c.published} poses published",
            file=sys.stderr,
            flush=True,
        )
        return 0
    finally:
        if worker is not None:
            worker.stop()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
