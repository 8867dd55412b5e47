"""Frozen configuration dataclasses of a synthetic world and its two recording sessions.

A :class:`WorldConfig` fully determines (with a seed) the scene, the map and query
trajectories and the effects applied to the query session. It converts to and from plain
JSON-able dicts (``to_dict`` / ``from_dict``). Invalid values raise ``ValueError``.
Units: metres, degrees, seconds, pixels.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _finite(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def _ints_at_least(low: int, *values: object) -> bool:
    return all(isinstance(v, int) and v >= low for v in values)


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole intrinsics, OpenCV pixel convention (top-left pixel centre at (0, 0)).

    ``cx`` / ``cy`` default (None) to ``width / 2`` / ``height / 2``.
    """

    width: int = 640
    height: int = 480
    fx: float = 500.0
    fy: float = 500.0
    cx: float | None = None
    cy: float | None = None

    def __post_init__(self) -> None:
        _require(
            _ints_at_least(16, self.width, self.height),
            f"camera size must be integers >= 16, got {self.width}x{self.height}",
        )
        _require(
            _finite(self.fx, self.fy) and self.fx > 0 and self.fy > 0,
            f"camera focal lengths must be positive, got {self.fx}, {self.fy}",
        )
        for key, limit in (("cx", self.width), ("cy", self.height)):
            v = getattr(self, key)
            _require(
                v is None or (_finite(v) and 0 <= v <= limit), f"camera {key} must lie in the image, got {v}"
            )

    @property
    def principal_point(self) -> tuple[float, float]:
        return (
            self.width / 2 if self.cx is None else float(self.cx),
            self.height / 2 if self.cy is None else float(self.cy),
        )

    def intrinsics(self) -> np.ndarray:
        """(3, 3) matrix K."""
        cx, cy = self.principal_point
        return np.array([[self.fx, 0.0, cx], [0.0, self.fy, cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SceneConfig:
    """The scene: ``kind`` "room" (office) or "corridor" (doors along the long walls).

    The room spans x in [0, size_x], z in [0, size_z] with a ceiling ``height`` above the
    floor. Boxes have (width, height, depth) uniform in [box_size_min, box_size_max] and
    stand at least ``box_clearance`` from both camera paths (so that they do not fill the
    view). ``px_per_m`` is the texture resolution (texels per metre).
    """

    kind: str = "room"
    size_x: float = 8.0
    size_z: float = 6.0
    height: float = 2.6
    n_boxes: int = 6
    box_size_min: tuple[float, float, float] = (0.4, 0.4, 0.4)
    box_size_max: tuple[float, float, float] = (1.4, 1.6, 0.9)
    n_posters: int = 12
    px_per_m: float = 200.0
    box_clearance: float = 0.8

    def __post_init__(self) -> None:
        _require(
            self.kind in ("room", "corridor"), f"scene kind must be 'room' or 'corridor', got {self.kind!r}"
        )
        _require(
            _finite(self.size_x, self.size_z, self.height)
            and min(self.size_x, self.size_z) >= 1.5
            and self.height >= 1.8,
            "scene must be at least 1.5 x 1.5 m and 1.8 m high, "
            f"got {self.size_x} x {self.size_z} x {self.height}",
        )
        _require(
            isinstance(self.n_boxes, int) and self.n_boxes >= 0,
            f"n_boxes must be a non-negative integer, got {self.n_boxes}",
        )
        _require(
            isinstance(self.n_posters, int) and self.n_posters >= 0,
            f"n_posters must be a non-negative integer, got {self.n_posters}",
        )
        object.__setattr__(self, "box_size_min", tuple(float(v) for v in self.box_size_min))
        object.__setattr__(self, "box_size_max", tuple(float(v) for v in self.box_size_max))
        lo, hi = self.box_size_min, self.box_size_max
        _require(
            len(lo) == 3 and len(hi) == 3 and all(0.1 <= a <= b for a, b in zip(lo, hi, strict=True)),
            f"box sizes must be 3 values with 0.1 <= min <= max, got {lo}, {hi}",
        )
        _require(hi[1] < self.height, f"boxes ({hi[1]} m) must be lower than the ceiling ({self.height} m)")
        _require(
            _finite(self.px_per_m) and 20 <= self.px_per_m <= 1000,
            f"px_per_m must be in [20, 1000], got {self.px_per_m}",
        )
        _require(
            _finite(self.box_clearance) and self.box_clearance >= 0,
            f"box_clearance must be >= 0, got {self.box_clearance}",
        )


@dataclass(frozen=True)
class TrajectoryConfig:
    """The map path and the query path derived from it.

    ``shape`` "loop": an ellipse ``wall_margin`` from the walls; "line": straight along the
    middle of the longer side, from ``wall_margin`` to the far wall minus ``wall_margin``.
    The query path has ``n_query`` poses on the same curve, shifted ``lateral_offset`` to the
    right of the direction of travel, turned by ``yaw_offset_deg`` plus a sinusoidal
    ``yaw_wobble_deg``. Cameras must stay ``min_clearance`` from walls and boxes.
    Timestamps are ``frame_period`` seconds apart, starting at 0.

    Camera mount (fixed per robot, every frame of a session): the camera is pitched down by
    ``mount_pitch_deg`` (its optical axis points below the horizon) and rolled by
    ``mount_roll_deg`` (positive: its right side, the x-axis, goes up), i.e. its
    ``cam_from_world`` rotation is ``R_x(pitch) R_z(roll) R_y(yaw)``
    (:func:`planarloc.synthetic.world.effects.tilt_rotation`). ``query_mount_pitch_deg`` /
    ``query_mount_roll_deg`` give the query robot another mount (None: the map robot's).
    Off-plane queries: the query camera is ``query_height_drop`` metres lower than
    ``camera_height``, plus ``query_height_wobble * sin(2π · 2 · i / n_query)`` lower at query
    frame ``i`` (e.g. drop 0.45, wobble 0.25: 0.2–0.7 m lower, a hand-held camera).
    The per-frame pitch/roll jitter of an uneven floor is ``EffectsConfig.tilt_deg``.
    """

    shape: str = "loop"
    n_map: int = 40
    n_query: int = 30
    camera_height: float = 1.0  # m
    wall_margin: float = 1.4  # m
    lateral_offset: float = 0.3  # m
    yaw_offset_deg: float = 20.0
    yaw_wobble_deg: float = 8.0
    min_clearance: float = 0.5  # m
    frame_period: float = 0.1
    mount_pitch_deg: float = 0.0
    mount_roll_deg: float = 0.0
    query_mount_pitch_deg: float | None = None
    query_mount_roll_deg: float | None = None
    query_height_drop: float = 0.0
    query_height_wobble: float = 0.0

    def query_mount_deg(self) -> tuple[float, float]:
        """(pitch, roll) in degrees of the query robot's camera mount."""
        return (
            self.mount_pitch_deg if self.query_mount_pitch_deg is None else self.query_mount_pitch_deg,
            self.mount_roll_deg if self.query_mount_roll_deg is None else self.query_mount_roll_deg,
        )

    def __post_init__(self) -> None:
        _require(
            self.shape in ("loop", "line"), f"trajectory shape must be 'loop' or 'line', got {self.shape!r}"
        )
        _require(
            _ints_at_least(2, self.n_map, self.n_query),
            f"n_map and n_query must be integers >= 2, got {self.n_map}, {self.n_query}",
        )
        _require(
            _finite(self.camera_height) and self.camera_height >= 0.1,
            f"camera_height must be >= 0.1 m, got {self.camera_height}",
        )
        _require(
            _finite(self.wall_margin, self.lateral_offset, self.yaw_offset_deg, self.yaw_wobble_deg),
            "trajectory values must be finite",
        )
        _require(
            _finite(self.min_clearance) and self.min_clearance >= 0,
            f"min_clearance must be >= 0, got {self.min_clearance}",
        )
        _require(
            _finite(self.frame_period) and self.frame_period > 0,
            f"frame_period must be positive, got {self.frame_period}",
        )
        mounts = (self.mount_pitch_deg, self.mount_roll_deg, *self.query_mount_deg())
        _require(
            _finite(*mounts) and all(abs(v) <= 45 for v in mounts),
            f"mount pitch and roll must be in [-45, 45] degrees, got {mounts}",
        )
        _require(
            _finite(self.query_height_drop, self.query_height_wobble) and self.query_height_wobble >= 0,
            "query_height_drop must be finite and query_height_wobble >= 0, "
            f"got {self.query_height_drop}, {self.query_height_wobble}",
        )
        lowest = self.camera_height - self.query_height_drop - self.query_height_wobble
        _require(
            lowest >= 0.1,
            f"query camera would come down to {lowest:.2f} m above the floor (camera_height "
            f"{self.camera_height} - query_height_drop {self.query_height_drop} - query_height_wobble "
            f"{self.query_height_wobble}); it must stay >= 0.1 m",
        )


@dataclass(frozen=True)
class EffectsConfig:
    """Changes applied to one session's renders.

    Image: ``gain`` and ``gamma`` (out = 255 gain (in/255)^gamma), a smooth brightness
    ramp of relative amplitude ``shading_gradient`` across the image at ``shading_angle_deg``,
    a Gaussian blur of std ``blur_sigma`` and Gaussian noise of std ``noise_sigma``.
    Pose: random pitch and roll up to ``tilt_deg`` per frame (uneven floor).
    Scene (query session only): ``moved_boxes`` boxes moved, ``added_boxes`` new boxes.
    """

    gain: float = 1.0
    gamma: float = 1.0
    shading_gradient: float = 0.0
    shading_angle_deg: float = 0.0
    noise_sigma: float = 0.0  # grey levels
    blur_sigma: float = 0.0  # px
    tilt_deg: float = 0.0
    moved_boxes: int = 0
    added_boxes: int = 0

    def __post_init__(self) -> None:
        _require(
            _finite(self.gain, self.gamma, self.shading_angle_deg) and self.gain > 0 and self.gamma > 0,
            f"gain and gamma must be positive, got {self.gain}, {self.gamma}",
        )
        _require(
            _finite(self.shading_gradient) and 0 <= self.shading_gradient < 1,
            f"shading_gradient must be in [0, 1), got {self.shading_gradient}",
        )
        _require(
            _finite(self.noise_sigma, self.blur_sigma) and self.noise_sigma >= 0 and self.blur_sigma >= 0,
            f"noise_sigma and blur_sigma must be >= 0, got {self.noise_sigma}, {self.blur_sigma}",
        )
        _require(
            _finite(self.tilt_deg) and 0 <= self.tilt_deg <= 10,
            f"tilt_deg must be in [0, 10], got {self.tilt_deg}",
        )
        _require(
            isinstance(self.moved_boxes, int)
            and isinstance(self.added_boxes, int)
            and self.moved_boxes >= 0
            and self.added_boxes >= 0,
            "moved_boxes and added_boxes must be non-negative integers, "
            f"got {self.moved_boxes}, {self.added_boxes}",
        )


@dataclass(frozen=True)
class WorldConfig:
    """A named world: camera, scene, trajectories and per-session effects."""

    name: str = "office"
    camera: CameraConfig = field(default_factory=CameraConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    map_effects: EffectsConfig = field(default_factory=EffectsConfig)
    query_effects: EffectsConfig = field(default_factory=EffectsConfig)

    def __post_init__(self) -> None:
        _require(
            isinstance(self.name, str) and self.name.strip() != "", "config name must be a non-empty string"
        )
        for key, cls in (
            ("camera", CameraConfig),
            ("scene", SceneConfig),
            ("trajectory", TrajectoryConfig),
            ("map_effects", EffectsConfig),
            ("query_effects", EffectsConfig),
        ):
            _require(isinstance(getattr(self, key), cls), f"WorldConfig.{key} must be a {cls.__name__}")
        _require(
            self.map_effects.moved_boxes == 0 and self.map_effects.added_boxes == 0,
            "map_effects cannot move or add boxes: the map session defines the scene",
        )
        tc = self.trajectory
        highest = max(tc.camera_height, tc.camera_height - tc.query_height_drop + tc.query_height_wobble)
        _require(
            highest < self.scene.height - 0.1,
            f"cameras go up to {highest:.2f} m: they must stay 0.1 m below the {self.scene.height} m ceiling",
        )
        _require(
            self.query_effects.moved_boxes <= self.scene.n_boxes,
            f"cannot move {self.query_effects.moved_boxes} of {self.scene.n_boxes} boxes",
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of JSON types (tuples become lists)."""
        return _jsonable(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WorldConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError."""
        parts = {
            "camera": CameraConfig,
            "scene": SceneConfig,
            "trajectory": TrajectoryConfig,
            "map_effects": EffectsConfig,
            "query_effects": EffectsConfig,
        }
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key == "name":
                kwargs[key] = value
            elif key in parts:
                kwargs[key] = _build(parts[key], value)
            else:
                raise ValueError(f"unknown WorldConfig key {key!r}")
        return cls(**kwargs)


def _build(cls: type, values: dict[str, Any]) -> Any:
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys: {sorted(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value
