"""Gravity of a map: the world's down direction, declared by the dataset or estimated from its poses.

Frames and signs (docs/conventions.md, "Gravity"):

* ``g_world``: (3,) unit vector, the direction of gravity (pointing **down**) in the map's world
  frame. Map poses are ``cam_from_world``, so the gravity seen by map camera ``i`` is
  ``g_cam_i = R_i · g_world`` (:func:`gravity_in_camera`); an upright camera has
  ``g_cam = (0, 1, 0)`` (camera y-axis down).
* Mount tilt of a camera: ``(pitch, roll) = pitch_roll_from_gravity(g_cam)``
  (:mod:`planarloc.gravity.upright`; pitch > 0 looks below the horizon, roll > 0 right side
  lower).

Where ``g_world`` comes from, first that applies:

1. ``option``: the user's ``up=`` dataset option (:func:`world_down_from_up`); ``up=estimate``
   ignores the format's declaration and estimates (3.);
2. ``declared``: the dataset format defines the world's up axis (:class:`WorldDown` on every
   :class:`~planarloc.map.posed_image.PosedImage` of the importer);
3. ``estimated`` (:func:`gravity_from_map_poses`): a ground robot's camera centres lie on the
   (locally level) floor plane, at a fixed height. The normal of the plane through the centres is
   gravity up to sign; the sign makes the cameras' y-axes point down. For collinear centres
   (a straight drive) the plane is undetermined: gravity is then the mean camera y-axis with its
   component along the line removed (the tilt about the line is taken from the cameras, i.e.
   assumed zero on average).

Whatever the source, the map cameras' tilt relative to ``g_world`` — the camera mount's pitch and
roll — is reported with its spread; a large spread means the cameras are not one rigidly mounted
camera on level ground, and the tilt assumed for queries without their own gravity is uncertain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.gravity.upright import pitch_roll_from_gravity, upright_from_cam_rotation
from planarloc.robust.pair_matches import unit_gravity

COLLINEAR_RATIO = 0.05
"""Centres whose second rms extent is below this fraction of the first are treated as a line."""
NOT_PLANAR_RATIO = 0.3
"""Centres whose plane residual (rms) exceeds this fraction of the second extent span 3D: no plane."""
TILT_SPREAD_WARN_DEG = 2.0
"""Robust spread (1.4826·MAD) of the mount pitch or roll above which ``map info`` warns."""
LARGE_TILT_WARN_DEG = 45.0
"""An estimated plane whose normal is this far from the cameras' median y-axis is suspicious."""

_AXES = {"x": 0, "y": 1, "z": 2}
ESTIMATE = "estimate"
"""``up=estimate``: ignore the format's declared gravity, estimate it from the map's poses."""


@dataclass(frozen=True)
class WorldDown:
    """A world's down direction given by the dataset format or by the user.

    Attributes:
        direction: (3,) unit vector of gravity (pointing down) in the world frame; None only for
            the user's ``up=estimate`` (estimate from the poses even if the format declares one).
        source: ``"declared"`` (the dataset format defines it) or ``"option"`` (``up=`` given).
        detail: where it comes from, for ``map info`` (e.g. ``"KITTI: world = first camera frame"``).
    """

    direction: tuple[float, float, float] | None
    source: str
    detail: str

    def __post_init__(self) -> None:
        if self.source not in ("declared", "option"):
            raise InputError(f"WorldDown.source: expected 'declared' or 'option', got {self.source!r}")
        if self.direction is None:
            if self.source != "option":
                raise InputError("WorldDown.direction: None (estimate) is only an option (up=estimate)")
            return
        g = unit_gravity("WorldDown.direction", self.direction)
        object.__setattr__(self, "direction", tuple(float(v) + 0.0 for v in g))  # no -0.0

    def to_dict(self) -> dict:
        direction = None if self.direction is None else list(self.direction)
        return {"direction": direction, "source": self.source, "detail": self.detail}

    @classmethod
    def from_dict(cls, d: dict) -> WorldDown:
        direction = None if d["direction"] is None else tuple(d["direction"])
        return cls(direction, d["source"], d.get("detail", ""))


def parse_up(value: object) -> np.ndarray:
    """The world's UP direction from an ``up=`` option value.

    Args:
        value: an axis name with optional sign (``"z"``, ``"+z"``, ``"-y"``), three numbers as a
            string (``"0,0,1"`` or ``"0 0 1"``) or a sequence of three numbers.

    Returns:
        (3,) unit up vector in the world frame (gravity is its negative).

    Raises:
        InputError: anything else, naming the value and the accepted forms.

    Example:
        >>> parse_up("-y")
        array([ 0., -1.,  0.])
    """
    hint = (
        "expected an axis (x, y, z with optional sign, e.g. -y), a vector 'ux,uy,uz' (e.g. 0,0,1) "
        f"or '{ESTIMATE}'"
    )
    if isinstance(value, str):
        text = value.strip().lower()
        if text.lstrip("+-") in _AXES and len(text) - len(text.lstrip("+-")) <= 1:
            v = np.zeros(3)
            v[_AXES[text.lstrip("+-")]] = -1.0 if text.startswith("-") else 1.0
            return v
        tokens = text.replace(",", " ").split()
        try:
            numbers = [float(t) for t in tokens]
        except ValueError:
            raise InputError(f"up={value!r}: {hint}") from None
    elif isinstance(value, (list, tuple, np.ndarray)):
        try:
            numbers = [float(t) for t in value]
        except (TypeError, ValueError):
            raise InputError(f"up={value!r}: {hint}") from None
    else:
        raise InputError(f"up={value!r}: {hint}")
    if len(numbers) != 3 or not all(math.isfinite(x) for x in numbers) or not any(numbers):
        raise InputError(f"up={value!r}: {hint}; got {len(numbers)} number(s)")
    v = np.array(numbers)
    return v / np.linalg.norm(v)


def world_down_from_up(value: object) -> WorldDown:
    """:class:`WorldDown` of the user's ``up=`` option (``source="option"``); see :func:`parse_up`.

    ``up=estimate`` gives ``direction=None``: estimate from the poses."""
    if isinstance(value, str) and value.strip().lower() == ESTIMATE:
        return WorldDown(None, "option", f"up={ESTIMATE}")
    if not isinstance(value, (list, tuple, np.ndarray)):  # a string: parse_up refuses anything else
        return WorldDown(tuple(-parse_up(value)), "option", f"up={value}")
    return WorldDown(tuple(-parse_up(value)), "option", f"up={list(value)}")


def _floats3(v: np.ndarray) -> tuple[float, float, float]:
    """A (3,) array as a tuple of Python floats."""
    return float(v[0]), float(v[1]), float(v[2])


def gravity_in_camera(pose: Pose, g_world: object) -> np.ndarray:
    """Gravity direction in a camera's frame.

    Args:
        pose: ``cam_from_world`` of the camera.
        g_world: (3,) gravity direction (down) in the world frame, any non-zero length.

    Returns:
        (3,) unit vector ``R · g_world / |g_world|`` in the camera frame (x right, y down,
        z forward); ``(0, 1, 0)`` for an upright camera.
    """
    if not isinstance(pose, Pose):
        raise InputError(f"pose: expected a planarloc Pose, got {type(pose).__name__}")
    return pose.R @ unit_gravity("g_world", g_world)


@dataclass(frozen=True)
class GravityReport:
    """What :func:`gravity_from_map_poses` found (stored in the map, printed by ``map info``).

    Attributes:
        g_world: (3,) unit gravity (down) in the world frame.
        source: ``"option"``, ``"declared"`` or ``"estimated"``.
        method: how it was obtained: ``"given"`` (option/declared), ``"plane"`` (normal of the
            centres' plane), ``"line"`` (collinear centres: mean camera y-axis ⟂ line) or
            ``"camera_y"`` (mean camera y-axis: one position, or centres spanning 3D).
        detail: human-readable origin.
        num_cameras: number of map poses.
        pitch_deg, roll_deg: mount tilt of the map cameras relative to ``g_world``: the pitch
            and roll of the cameras' median gravity direction (module docstring).
        pitch_spread_deg, roll_spread_deg: robust spread (1.4826·MAD) of the per-camera values.
        pitch_max_dev_deg, roll_max_dev_deg: largest deviation of one camera from the median.
        plane_rms: rms distance of the centres to the fitted plane (map units), ``method="plane"``
            only; None otherwise.
        extent: rms extents of the centres along their principal axes (map units).
        warnings: one sentence per problem found (inconsistent tilt, no level plane, ...).
    """

    g_world: tuple[float, float, float]
    source: str
    method: str
    detail: str
    num_cameras: int
    pitch_deg: float
    roll_deg: float
    pitch_spread_deg: float
    roll_spread_deg: float
    pitch_max_dev_deg: float
    roll_max_dev_deg: float
    plane_rms: float | None = None
    extent: tuple[float, float, float] = (0.0, 0.0, 0.0)
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def g_world_array(self) -> np.ndarray:
        return np.array(self.g_world, dtype=float)

    @property
    def mount_gravity(self) -> np.ndarray:
        """(3,) gravity in the camera frame of the map's median mount tilt."""
        return upright_from_cam_rotation(self.pitch_deg, self.roll_deg).T @ np.array([0.0, 1.0, 0.0])

    def to_dict(self) -> dict:
        d = asdict(self)
        d["g_world"] = list(self.g_world)
        d["extent"] = list(self.extent)
        d["warnings"] = list(self.warnings)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GravityReport:
        d = dict(d)
        d["g_world"] = tuple(float(v) for v in d["g_world"])
        d["extent"] = tuple(float(v) for v in d.get("extent", (0.0, 0.0, 0.0)))
        d["warnings"] = tuple(d.get("warnings", ()))
        return cls(**d)

    def summary_lines(self) -> list[str]:
        """Lines for ``map info``."""
        g = ", ".join(f"{v:+.4f}" for v in self.g_world)
        how = {
            "given": "",
            "plane": ", normal of the camera centres' plane",
            "line": ", collinear centres: mean camera y-axis orthogonal to the line",
            "camera_y": ", mean camera y-axis",
        }[self.method]
        lines = [f"gravity (down, world frame): ({g})  source: {self.source}{how}"]
        if self.detail:
            lines.append(f"  {self.detail}")
        lines.append(
            f"  mount tilt of the {self.num_cameras} map cameras: pitch {self.pitch_deg:+.2f}° "
            f"(spread {self.pitch_spread_deg:.2f}°, max dev {self.pitch_max_dev_deg:.2f}°), "
            f"roll {self.roll_deg:+.2f}° (spread {self.roll_spread_deg:.2f}°, max dev "
            f"{self.roll_max_dev_deg:.2f}°)"
        )
        if self.plane_rms is not None:
            lines.append(
                f"  plane fit residual: {self.plane_rms:.4f} rms (map units) over extents "
                + " x ".join(f"{e:.3g}" for e in self.extent)
            )
        lines += [f"  warning: {w}" for w in self.warnings]
        return lines


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _spread(values: np.ndarray, center: float) -> tuple[float, float]:
    dev = np.abs(_wrap_deg(values - center))
    return float(1.4826 * np.median(dev)), float(dev.max())


def mount_tilt(poses: Sequence[Pose], g_world: object) -> tuple[np.ndarray, np.ndarray]:
    """Per-camera pitch and roll (degrees) relative to ``g_world``.

    Args:
        poses: N ``cam_from_world`` poses.
        g_world: (3,) gravity (down) in the world frame.

    Returns:
        ``(pitch (N,), roll (N,))`` as :func:`planarloc.gravity.upright.pitch_roll_from_gravity`
        of ``R_i · g_world``.
    """
    g = unit_gravity("g_world", g_world)
    tilts = [pitch_roll_from_gravity(p.R @ g) for p in poses]
    arr = np.array(tilts, dtype=float).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def _check_poses(poses: Sequence[Pose]) -> list[Pose]:
    poses = list(poses)
    if not poses:
        raise InputError("poses: expected at least one cam_from_world pose, got none")
    for i, p in enumerate(poses):
        if not isinstance(p, Pose):
            raise InputError(f"poses[{i}]: expected a planarloc Pose, got {type(p).__name__}")
    return poses


def _estimate(poses: list[Pose]) -> tuple[np.ndarray, str, str, float | None, np.ndarray, list[str]]:
    centers = np.array([p.center for p in poses])
    y_axes = np.array([p.R[1] for p in poses])  # camera y-axis in world coordinates (row 1 of R)
    mean_y = y_axes.mean(axis=0)
    warnings: list[str] = []
    n = len(poses)
    if n >= 2:
        _, s, vt = np.linalg.svd(centers - centers.mean(axis=0), full_matrices=n < 3)  # vt is 3x3; no n x n U
        s = np.concatenate([s, np.zeros(3 - len(s))]) / math.sqrt(n)
    else:
        s, vt = np.zeros(3), np.eye(3)
    extent = s
    if s[0] <= 1e-9 * max(1.0, float(np.abs(centers).max())):
        g = mean_y
        return g, "camera_y", "all cameras at one position: mean camera y-axis", None, extent, warnings
    if n < 3 or s[1] < COLLINEAR_RATIO * s[0]:
        d = vt[0]
        g = mean_y - (mean_y @ d) * d
        if np.linalg.norm(g) < 1e-6:
            raise InputError(
                "map poses: the cameras' y-axes are parallel to the line of their centres; "
                "gravity cannot be estimated, pass the dataset option up=..."
            )
        return (
            g,
            "line",
            "camera centres are collinear: the tilt about the line direction is not observable "
            "and taken from the cameras (assumed zero on average)",
            None,
            extent,
            warnings,
        )
    if s[2] > NOT_PLANAR_RATIO * s[1]:
        warnings.append(
            f"the camera centres do not lie on a plane (residual {s[2]:.3g} vs extent {s[1]:.3g} rms): "
            "gravity is the mean camera y-axis, which assumes upright cameras on average; pass the dataset "
            "option up=..."
        )
        return mean_y, "camera_y", "centres span 3D: mean camera y-axis", None, extent, warnings
    normal = vt[2]
    if normal @ mean_y < 0:
        normal = -normal
    return normal, "plane", "", float(s[2]), extent, warnings


def _tilt_spread(
    poses: list[Pose], g: np.ndarray
) -> tuple[np.ndarray, float, float, float, float, float, float]:
    """The map cameras' mount tilt relative to unit gravity ``g``: their median gravity direction,
    its pitch and roll, and the spread and largest deviation of the pitch and of the roll."""
    g_cams = np.array([p.R @ g for p in poses])
    median_g = np.median(g_cams, axis=0)
    if not np.linalg.norm(median_g) > 1e-9:
        median_g = g_cams.mean(axis=0) if np.linalg.norm(g_cams.mean(axis=0)) > 1e-9 else g_cams[0]
    pitch0, roll0 = pitch_roll_from_gravity(median_g)
    pitch, roll = mount_tilt(poses, g)
    p_spread, p_max = _spread(pitch, pitch0)
    r_spread, r_max = _spread(roll, roll0)
    return median_g, float(pitch0), float(roll0), p_spread, p_max, r_spread, r_max


def _estimate_advice(poses: list[Pose]) -> str:
    """Advice for an inconsistent tilt under a format's declared gravity: the dataset option
    ``up=estimate``, only if the gravity estimated from the poses makes the tilt consistent
    (checked here, so that following the advice removes the problem, without the large-tilt
    warning instead); else nothing."""
    try:
        g = _estimate(poses)[0]
    except InputError:
        return ""
    median_g, _, _, p_spread, _, r_spread, _ = _tilt_spread(poses, g / np.linalg.norm(g))
    tilt = math.degrees(math.acos(float(np.clip(median_g[1] / np.linalg.norm(median_g), -1.0, 1.0))))
    if max(p_spread, r_spread) > TILT_SPREAD_WARN_DEG or tilt > LARGE_TILT_WARN_DEG:
        return ""
    return (
        f"; the format's declared gravity is off: gravity estimated from the map's poses makes the tilt "
        f"consistent (spread pitch {p_spread:.1f}°, roll {r_spread:.1f}°); build the map with the dataset "
        "option up=estimate (command line: --dataset-option up=estimate)"
    )


def gravity_from_map_poses(
    poses: Sequence[Pose], declared: WorldDown | None = None
) -> tuple[np.ndarray, GravityReport]:
    """The world's gravity direction of a map and the cameras' mount tilt relative to it.

    Args:
        poses: N >= 1 ``cam_from_world`` poses of the map images (world frame = the map's).
        declared: the world's down direction if the dataset or the user gives it; then it is
            used as is and only the mount tilt is measured (``up=estimate``, direction None:
            estimated all the same).

    Returns:
        ``(g_world (3,) unit, report)``: gravity pointing down in the world frame, and the
        :class:`GravityReport` (source, method, mount pitch/roll median and spread, plane
        residual, warnings).

    Raises:
        InputError: no poses, non-Pose items, or collinear centres along the cameras' y-axes.

    Method (``declared is None``): SVD of the centred camera centres with rms extents
    ``s1 >= s2 >= s3``. Plane (``s2 >= 0.05·s1`` and ``s3 <= 0.3·s2``): gravity = the normal
    (third singular vector), signed so that the mean camera y-axis (row 1 of ``R``) points along
    it. Line (``s2 < 0.05·s1``): gravity = the mean camera y-axis minus its component along the
    line. Otherwise the mean camera y-axis, with a warning.

    Example:
        >>> g, rep = gravity_from_map_poses(poses)          # doctest: +SKIP
        >>> rep.source, rep.pitch_deg                        # doctest: +SKIP
        ('estimated', 8.0)
    """
    poses = _check_poses(poses)
    if declared is not None and not isinstance(declared, WorldDown):
        raise InputError(f"declared: expected a WorldDown, got {type(declared).__name__}")
    warnings: list[str]
    if declared is not None and declared.direction is not None:
        g, method, detail, plane_rms, warnings = (
            np.array(declared.direction),
            "given",
            declared.detail,
            None,
            [],
        )
        centers = np.array([p.center for p in poses])
        s = (
            np.linalg.svd(centers - centers.mean(axis=0), compute_uv=False) / math.sqrt(len(poses))
            if len(poses) >= 2
            else np.zeros(3)
        )
        extent = np.concatenate([s, np.zeros(3 - len(s))])
        source = declared.source
    else:
        g, method, detail, plane_rms, extent, warnings = _estimate(poses)
        source = "estimated"
        if declared is not None:  # up=estimate
            detail = f"{declared.detail}: {detail}" if detail else declared.detail
    g = g / np.linalg.norm(g)
    median_g, pitch0, roll0, p_spread, p_max, r_spread, r_max = _tilt_spread(poses, g)
    if max(p_spread, r_spread) > TILT_SPREAD_WARN_DEG:
        warnings.append(
            f"the cameras' tilt relative to gravity is inconsistent (spread pitch {p_spread:.1f}°, roll "
            f"{r_spread:.1f}°): not one rigid mount on level ground; queries without their own gravity get "
            "the median tilt, which may be wrong for them"
            + (_estimate_advice(poses) if source == "declared" else "")
        )
    tilt = math.degrees(math.acos(float(np.clip(median_g[1] / np.linalg.norm(median_g), -1.0, 1.0))))
    if method in ("plane", "line") and tilt > LARGE_TILT_WARN_DEG:
        warnings.append(
            f"the cameras are tilted {tilt:.0f}° from the estimated gravity: the centres' {method} is "
            "probably not level (e.g. a handheld or vertical path); pass the dataset option up=..."
        )
    report = GravityReport(
        g_world=_floats3(g),
        source=source,
        method=method,
        detail=detail,
        num_cameras=len(poses),
        pitch_deg=float(pitch0),
        roll_deg=float(roll0),
        pitch_spread_deg=p_spread,
        roll_spread_deg=r_spread,
        pitch_max_dev_deg=p_max,
        roll_max_dev_deg=r_max,
        plane_rms=plane_rms,
        extent=_floats3(extent),
        warnings=tuple(warnings),
    )
    return g, report
