"""The ROS 2 node's parameters (:class:`NodeSettings`), their checks, and the files that use them.

This module does not import rclpy, so that ``planarloc ros2 --help`` can list the
parameters (:func:`parameters_listing`) and tests can check the packaged files against them:
``share/params.yaml`` (every parameter with its default, :func:`params_yaml`),
``share/planarloc.launch.py`` (ROS 2 launch) and ``share/planarloc.rviz`` (:data:`SHARE_DIR`).
"""

from __future__ import annotations

import itertools
import re
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

from planarloc.features.registry import FEATURE_TYPES
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.ros_messages import rectified_topic
from planarloc.io.rosbag import parse_transform
from planarloc.localize.localizer_config import SHARED_SETTINGS as LOCALIZER_SETTINGS
from planarloc.localize.localizer_config import LocalizerConfig, localizer_config_from
from planarloc.localize.stream_config import FIX_MODES, SequenceConfig, sequence_config_from
from planarloc.robust.options import Method, Structure

NODE_NAME = "planarloc"
#: the packaged launch file, parameter file and rviz configuration (``planarloc ros2 --share-dir``)
SHARE_DIR = Path(__file__).resolve().parent / "share"
#: ``map_frame_convention`` values: ``z_up`` (REP-103/105, gravity along -z) or ``world`` (the map's own)
MAP_FRAME_CONVENTIONS = ("z_up", "world")
#: parameters every ROS 2 node has (rclpy declares them)
ROS_PARAMETERS = ("use_sim_time",)

# The defaults of the settings the node shares with the library are the library's (a test checks it):
_LOC = LocalizerConfig()
_SEQ = SequenceConfig()
#: ``max_published_std_m``'s default, a node-only limit (m): deliberately looser than the stream's
#: ``SequenceConfig.max_pose_std_m`` (0.3 m), which already calls a frame with a larger std ``lost``;
#: measured in BENCHMARKS.md ("The node's publishing limit"): 100 / 97.4 / 100 % published within
#: 0.25 m at 10 Hz without odometry, against 81.6 / 97.4 / 97.5 % with a 0.3 m limit.
MAX_PUBLISHED_STD_M = 0.5


@dataclass(frozen=True)
class NodeSettings:
    """The node's ROS parameters (``--ros-args -p name:=value`` or ``--params-file``) and their defaults.

    Every field has one entry below ("name: meaning"): ``planarloc ros2 --help`` and
    ``share/params.yaml`` are generated from it (:func:`parameter_help`).

    Attributes:
        map: the map file (``--map``, which takes precedence over a parameter file).
        image_topic: camera images (``sensor_msgs/Image``; a name ending in /compressed:
            ``CompressedImage``).
        camera_info_topic: the camera's ``CameraInfo``; while none has been received, the map's
            camera is used if the map has exactly one (a warning, once).
        image_qos: ``sensor_data`` (best effort; takes reliable publishers too) or ``reliable``.
        odom_topic: ``nav_msgs/Odometry`` of the base; empty: no odometry (and no map -> odom).
        initialpose_topic: an initial pose (rviz's "2D Pose Estimate") restarts the stream.
        pose_topic: the published ``PoseWithCovarianceStamped`` (in ``map_frame``).
        diagnostics_topic: one ``DiagnosticArray`` per frame.
        map_frame: the frame of the published poses and the parent of map -> odom.
        odom_frame: the odometry's frame, the child of map -> odom.
        base_frame: the robot's frame whose pose is published (when base -> camera is known).
        map_frame_convention: ``z_up`` (REP-103/105: ``map_frame`` is the map's world rotated so
            that gravity is -z, x along the world's x in the ground plane;
            ``planarloc.ros2.conversions.map_from_world_from_gravity``) or ``world``
            (``map_frame`` is the map's world itself, e.g. y down for KITTI).
        camera_frame: the image's frame; empty: the image's ``header.frame_id``.
        base_to_camera: ``'x y z qx qy qz qw'``, the camera's pose in ``base_frame`` (as
            ``static_transform_publisher``), used when TF has no base -> camera; empty: TF only.
        odom_tolerance_s: odometry is interpolated at the image's stamp from samples at most
            ``2 odom_tolerance_s`` apart, else taken from one within ``odom_tolerance_s``.
        transform_tolerance_s: map -> odom is stamped this much after the image (AMCL's
            ``transform_tolerance``), so that TF lookups up to that time succeed.
        tf_broadcast: publish map -> odom on /tf (AMCL's ``tf_broadcast``); false: poses only.
        publish_predicted: also publish ``predicted`` frames (the motion model's pose; it keeps
            its promise like a localized one, its covariance grown with what the motion model does
            not know); false: ``localized`` frames only.
        max_position_std_m: the single-frame estimator's limit: a fix with a larger position std
            (worst axis) is a failure (``RansacOptions.max_position_std_m``).
        max_published_std_m: no pose with a larger position std (worst axis) is published: a
            pose keeps its promise (within 3 std + 5 cm), so none is then more than 1.55 m off,
            and the stream's stds are conservative (the published errors stay under 0.3 m on the
            shared KITTI; BENCHMARKS.md, "Stream trust").
        method: the hypothesis family (``planarloc localize --method``).
        structure: ``tracks`` (also 2D-3D constraints from points triangulated between map
            images) or ``none`` (2D-2D only) (``planarloc localize --structure``).
        top_n: retrieved map images per fix (``planarloc localize --top-n``).
        features: the feature type the map must have been built with (a type of ``planarloc
            localize --features``); another is refused when the node starts; empty: the map's own
            (frames always use the map's features).
        seed: the RANSAC seed (``planarloc localize --seed``).
        coarse_keypoints: a fix localizes from this many strongest keypoints first, from all only
            when that fails (``planarloc localize --coarse-keypoints``); -1: the map's feature
            type's (2048 for xfeat with ``structure`` ``tracks``, none otherwise); 0: none.
        window: poses kept in the stream's sliding-window pose graph.
        local_top_n: map images nearest to the predicted pose used for a fix.
        vo_model: frame-to-frame motion model: ``planar``, ``6dof`` or ``auto``.
        kidnap_confirmations: consistent rejected fixes needed to re-initialise the stream.
        fixes: ``background`` (absolute fixes in a worker thread, frames posed by tracking
            meanwhile) or ``wait`` (each frame waits for its fix: deterministic, for replays).
        queue_size: frames waiting for the worker at most (1: only the newest); ``latency_ms``
            includes the wait.
    """

    map: str = ""
    image_topic: str = "/camera/image_raw"
    camera_info_topic: str = "/camera/camera_info"
    image_qos: str = "sensor_data"
    odom_topic: str = "/odom"
    initialpose_topic: str = "/initialpose"
    pose_topic: str = "/planarloc/pose"
    diagnostics_topic: str = "/diagnostics"
    map_frame: str = "map"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    map_frame_convention: str = "z_up"
    camera_frame: str = ""
    base_to_camera: str = ""
    odom_tolerance_s: float = 0.1
    transform_tolerance_s: float = 1.0
    tf_broadcast: bool = True
    publish_predicted: bool = True
    max_position_std_m: float = _LOC.ransac.max_position_std_m
    max_published_std_m: float = MAX_PUBLISHED_STD_M
    method: str = Method(_LOC.method).value
    structure: str = Structure(_LOC.ransac.structure).value
    top_n: int = _LOC.top_n
    features: str = ""
    seed: int = int(_LOC.ransac.seed or 0)
    coarse_keypoints: int = -1
    window: int = _SEQ.window
    local_top_n: int = _SEQ.local_top_n
    vo_model: str = _SEQ.vo_model
    kidnap_confirmations: int = _SEQ.kidnap_confirmations
    fixes: str = _SEQ.fixes
    queue_size: int = 5

    def __post_init__(self) -> None:
        if not self.map:
            raise InputError("parameter map: give the map file (--map MAP.db or -p map:=MAP.db)")
        choices = {
            "method": [m.value for m in Method],
            "structure": [s.value for s in Structure],
            "fixes": list(FIX_MODES),
            "image_qos": ["sensor_data", "reliable"],
            "map_frame_convention": list(MAP_FRAME_CONVENTIONS),
        }
        if self.features:
            choices["features"] = list(FEATURE_TYPES)
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise InputError(
                    f"parameter {name}: expected one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        for name in ("odom_tolerance_s", "max_position_std_m", "max_published_std_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"parameter {name}: expected a number > 0, got {getattr(self, name)}")
        if self.coarse_keypoints < -1:
            raise InputError(
                "parameter coarse_keypoints: expected -1 (the feature type's), 0 or more, "
                f"got {self.coarse_keypoints}"
            )
        if self.queue_size < 1:
            raise InputError(f"parameter queue_size: expected an integer >= 1, got {self.queue_size}")
        if not self.transform_tolerance_s >= 0:
            raise InputError(
                f"parameter transform_tolerance_s: expected >= 0, got {self.transform_tolerance_s}"
            )
        for name in (
            "image_topic",
            "camera_info_topic",
            "pose_topic",
            "diagnostics_topic",
            "map_frame",
            "odom_frame",
            "base_frame",
        ):
            if not getattr(self, name):
                raise InputError(f"parameter {name}: must not be empty")

    def localizer_config(self) -> LocalizerConfig:
        """The fixes' single-frame localizer configuration (``method`` and ``structure`` parsed here,
        the ROS parameters' edge; what is not a parameter keeps :class:`LocalizerConfig`'s default)."""
        coarse = None if self.coarse_keypoints == -1 else self.coarse_keypoints
        return localizer_config_from(
            self, (*LOCALIZER_SETTINGS, "max_position_std_m"), coarse_keypoints=coarse
        )

    def sequence_config(self) -> SequenceConfig:
        """The stream's configuration (what is not a parameter keeps :class:`SequenceConfig`'s default)."""
        return sequence_config_from(self)

    @property
    def base_from_camera(self) -> Pose | None:
        return (
            parse_transform(self.base_to_camera, "parameter base_to_camera") if self.base_to_camera else None
        )

    @property
    def rectified(self) -> bool:
        """A rectified image topic (``image_rect``, …; :func:`planarloc.io.ros_messages.rectified_topic`):
        undistorted, its CameraInfo's ``P`` applies."""
        return rectified_topic(self.image_topic)

    @property
    def compressed(self) -> bool:
        return self.image_topic.rstrip("/").endswith("/compressed")


PARAMETERS = tuple(f.name for f in fields(NodeSettings))


def parameter_help() -> dict[str, str]:
    """``{parameter: meaning}`` from the "Attributes:" section of :class:`NodeSettings`' docstring
    (a group "a, b: text" gives each name the text), in field order.

    Raises:
        RuntimeError: a field without an entry, or an entry that is not a field (the docstring and
            the fields disagree: a bug, caught by the tests).
    """
    doc = textwrap.dedent((NodeSettings.__doc__ or "").split("Attributes:", 1)[-1])
    entries: list[list[str]] = []
    for line in doc.splitlines():
        head = re.match(r"^([a-z_][a-z0-9_]*(?:, [a-z_][a-z0-9_]*)*): (.*)$", line)
        if head and not line.startswith(" "):
            entries.append([head.group(1), head.group(2).strip()])
        elif line.strip() and entries:
            entries[-1][1] += " " + line.strip()
    found: dict[str, str] = {}
    for names, text in entries:
        for name in names.split(", "):
            found[name] = text.replace("``", "")
    missing, extra = set(PARAMETERS) - set(found), set(found) - set(PARAMETERS)
    if missing or extra:
        raise RuntimeError(
            f"NodeSettings' docstring and fields disagree: undocumented {sorted(missing)}, "
            f"not fields {sorted(extra)}"
        )
    return {name: found[name] for name in PARAMETERS}


def yaml_value(value: object) -> str:
    """A default as YAML writes it (``''`` for the empty string, ``true``/``false``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return repr(value)


def parameters_listing(width: int = 100) -> str:
    """The parameters with their defaults and meanings, for ``planarloc ros2 --help``."""
    lines = ["", "", "parameters (--ros-args -p NAME:=VALUE or --params-file FILE; name = default: meaning):"]
    for name, text in parameter_help().items():
        default = getattr(NodeSettings, name)
        lines += textwrap.wrap(
            f"{name} = {yaml_value(default)}: {text}", width, initial_indent="  ", subsequent_indent="      "
        )
    return "\n".join(lines)


def params_yaml() -> str:
    """The text of ``share/params.yaml``: every parameter with its default, its meaning as a comment.

    The packaged file is this text (a test compares them); after changing :class:`NodeSettings`,
    rewrite it with ``python -c "from planarloc.ros2.settings import *; (SHARE_DIR / 'params.yaml')
    .write_text(params_yaml())"``.
    """
    out = [
        "# planarloc ros2: every parameter with its default "
        "(generated by planarloc.ros2.settings.params_yaml).",
        "# Copy it, change what you need, and pass it: "
        "planarloc ros2 --map MAP.db --ros-args --params-file FILE",
        "# (--map takes precedence over `map` here).",
        f"{NODE_NAME}:",
        "  ros__parameters:",
    ]
    for name, text in parameter_help().items():
        out += textwrap.wrap(text, 96, initial_indent="    # ", subsequent_indent="    # ")
        out.append(f"    {name}: {yaml_value(getattr(NodeSettings, name))}")
    return "\n".join(out) + "\n"


def check_parameter_names(ros_args: Sequence[str]) -> None:
    """Reject ``-p name:=value`` overrides and ``--params-file`` entries of parameters the node does
    not have (ROS would ignore them silently).

    Raises:
        InputError: an unknown name, a ``-p`` without ``:=value``, or a parameter file that cannot
            be read or is not YAML (each naming the argument).
    """
    for flag, value in itertools.pairwise(ros_args):
        if flag in ("-p", "--param"):
            name = value.split(":=", 1)[0]
            if ":=" not in value or not value.split(":=", 1)[1]:
                raise InputError(
                    f"--ros-args {flag} {value}: expected name:=value (an empty string: name:='')"
                )
            if name.rpartition(".")[2] not in PARAMETERS and name not in ROS_PARAMETERS:
                raise InputError(
                    f"--ros-args {flag} {value}: unknown parameter {name!r}; parameters: "
                    f"{', '.join(PARAMETERS)}"
                )
        elif flag == "--params-file":
            unknown = [n for n in params_file_names(value) if n not in PARAMETERS and n not in ROS_PARAMETERS]
            if unknown:
                raise InputError(
                    f"--ros-args --params-file {value}: unknown parameter {unknown[0]!r}; parameters: "
                    f"{', '.join(PARAMETERS)}"
                )


def _applies_to_node(key: str) -> bool:
    """Whether a ROS parameter file's node key matches this node (``planarloc``, ``/planarloc``,
    ``/**``, ``/**/planarloc``)."""
    key = str(key).strip("/")
    return key in (NODE_NAME, "**", "*") or key.endswith("/" + NODE_NAME)


def params_file_names(path: str | Path) -> list[str]:
    """The parameter names a ROS 2 parameter file sets for this node (nested dictionaries as dotted
    names), in file order.

    Raises:
        InputError: a file that cannot be read or is not a YAML mapping.
    """
    import yaml  # a dependency of rclpy (the ros2 extra)

    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"--ros-args --params-file {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise InputError(f"--ros-args --params-file {path}: not YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, dict):
        raise InputError(
            f"--ros-args --params-file {path}: expected a mapping 'node: ros__parameters: ...', "
            f"got {type(data).__name__}"
        )
    names: list[str] = []

    def flat(d: dict, prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                flat(v, f"{prefix}{k}.")
            else:
                names.append(f"{prefix}{k}")

    def walk(d: dict, key: str) -> None:
        params = d.get("ros__parameters")
        if isinstance(params, dict) and _applies_to_node(key):
            flat(params, "")
        for k, v in d.items():
            if k != "ros__parameters" and isinstance(v, dict):
                walk(v, f"{key}/{k}")

    walk(data, "")
    return names
