"""Camera models with COLMAP's names and parameter order (``src/colmap/sensor/models.h``).

==================  ==========================================  ===============================
model               params                                      distortion of ``(x, y) = X/Z``
==================  ==========================================  ===============================
``SIMPLE_PINHOLE``  ``f, cx, cy``                               none
``PINHOLE``         ``fx, fy, cx, cy``                          none
``SIMPLE_RADIAL``   ``f, cx, cy, k``                            ``(x, y) (1 + k r²)``
``RADIAL``          ``f, cx, cy, k1, k2``                       ``(x, y) (1 + k1 r² + k2 r⁴)``
``OPENCV``          ``fx, fy, cx, cy, k1, k2, p1, p2``          radial + tangential (OpenCV)
``OPENCV_FISHEYE``  ``fx, fy, cx, cy, k1, k2, k3, k4``          ``(x, y) θ_d / r`` (below)
==================  ==========================================  ===============================

with ``r² = x² + y²``; the pixel is ``(fx x_d + cx, fy y_d + cy)`` (``fx = fy = f`` for the
one-focal models). ``OPENCV_FISHEYE`` is OpenCV's ``cv2.fisheye`` model (Kannala-Brandt,
equidistant): a ray at angle ``θ`` from the optical axis lands at radius
``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`` from the principal point, in the ray's azimuth.

Pixel coordinates follow COLMAP/OpenCV: the centre of the top-left pixel is (0.5, 0.5) in
COLMAP and (0, 0) in OpenCV; planarloc uses the **OpenCV** convention, like the intrinsics
users calibrate with OpenCV, KITTI and TUM. ``cam_from_img`` maps pixels to undistorted
normalized coordinates ``(x/z, y/z)``; ``img_from_cam`` is its inverse.

Where a distortion is not invertible the result is NaN, never a wrong ray: beyond the radius
where the radial map folds back (:func:`max_undistorted_radius`), beyond the angle where the
fisheye's ``θ_d(θ)`` stops increasing (:func:`max_fisheye_angle`), and, for ``cam_from_img``
and ``bearings_from_img``, fisheye rays at 90° or more from the axis, which normalized
coordinates cannot represent; :meth:`Camera.unit_bearings_from_img` returns those.

References: COLMAP ``src/colmap/sensor/models.h`` (``SimpleRadialCameraModel``,
``RadialCameraModel``, ``OpenCVFisheyeCameraModel``); J. Kannala, S. Brandt, "A generic camera
model and calibration method for conventional, wide-angle, and fish-eye lenses", TPAMI 2006:
its radially symmetric polynomial ``r(θ)`` with the leading coefficient 1 and, as in OpenCV,
terms up to ``θ⁹``. Deviation: for ``OPENCV_FISHEYE``,
``img_from_cam`` of 3D points uses ``θ = atan2(r, z)`` and so also projects points with
``z <= 0`` (COLMAP requires ``z > 0``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar

import numpy as np

from planarloc.geometry.validation import InputError, check_array


class CameraModel(str, Enum):
    """The supported camera models, in COLMAP's id order."""

    SIMPLE_PINHOLE = "SIMPLE_PINHOLE"
    PINHOLE = "PINHOLE"
    SIMPLE_RADIAL = "SIMPLE_RADIAL"
    RADIAL = "RADIAL"
    OPENCV = "OPENCV"
    OPENCV_FISHEYE = "OPENCV_FISHEYE"


#: Parameter names of each model, in COLMAP order.
PARAM_NAMES = {
    CameraModel.SIMPLE_PINHOLE: ("f", "cx", "cy"),
    CameraModel.PINHOLE: ("fx", "fy", "cx", "cy"),
    CameraModel.SIMPLE_RADIAL: ("f", "cx", "cy", "k"),
    CameraModel.RADIAL: ("f", "cx", "cy", "k1", "k2"),
    CameraModel.OPENCV: ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    CameraModel.OPENCV_FISHEYE: ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
NUM_PARAMS = {model: len(names) for model, names in PARAM_NAMES.items()}

#: COLMAP models planarloc does not support yet: rejected with their own message.
UNSUPPORTED_COLMAP_MODELS = (
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_DIVISION",
    "DIVISION",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "EUCM",
    "EQUIRECTANGULAR",
)

_ONE_FOCAL = frozenset({CameraModel.SIMPLE_PINHOLE, CameraModel.SIMPLE_RADIAL, CameraModel.RADIAL})
#: The two-focal model that :meth:`Camera.scaled` turns a one-focal model into.
_TWO_FOCAL = {
    CameraModel.SIMPLE_PINHOLE: CameraModel.PINHOLE,
    CameraModel.SIMPLE_RADIAL: CameraModel.OPENCV,
    CameraModel.RADIAL: CameraModel.OPENCV,
}


@dataclass(frozen=True)
class Camera:
    """An intrinsic camera model.

    Attributes:
        model: a :class:`CameraModel` name, e.g. ``"PINHOLE"`` (case-insensitive).
        width, height: image size in pixels.
        params: model parameters in COLMAP order (see module docstring).

    Example:
        >>> cam = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
        >>> cam.cam_from_img([[320.0, 240.0]])
        array([[0., 0.]])
    """

    model: CameraModel | str
    width: int
    height: int
    params: tuple[float, ...]

    #: The models the constructor accepts (named in its error for any other).
    SUPPORTED_MODELS: ClassVar[tuple[CameraModel, ...]] = tuple(CameraModel)

    def __post_init__(self) -> None:
        name = str(getattr(self.model, "value", self.model)).upper()
        supported = ", ".join(m.value for m in self.SUPPORTED_MODELS)
        if name in UNSUPPORTED_COLMAP_MODELS:
            raise InputError(
                f"Camera.model: COLMAP model {name} is not supported yet; supported: {supported}"
            )
        try:
            model = CameraModel(name)
        except ValueError:
            raise InputError(f"Camera.model: unknown model {self.model!r}; supported: {supported}") from None
        params = tuple(float(p) for p in check_array("Camera.params", self.params, (None,)))
        if len(params) != NUM_PARAMS[model]:
            raise InputError(
                f"Camera.params: {model.value} takes {NUM_PARAMS[model]} parameters, got {len(params)} "
                f"(expected {', '.join(PARAM_NAMES[model])})"
            )
        width, height = _pixel_count("width", self.width), _pixel_count("height", self.height)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        if min(self.focal) <= 0:
            focal = params[:1] if model in _ONE_FOCAL else params[:2]
            raise InputError(f"Camera.params: focal lengths must be positive, got {focal}")

    @classmethod
    def from_K(cls, K: object, width: int, height: int, dist: object | None = None) -> Camera:
        """From a 3x3 calibration matrix and optional OpenCV ``(k1, k2, p1, p2)`` distortion."""
        K = check_array("K", K, (3, 3))
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if dist is not None and np.any(np.asarray(dist, dtype=float) != 0):
            d = check_array("dist", dist, (4,))
            return cls(CameraModel.OPENCV, width, height, (fx, fy, cx, cy, *d))
        return cls(CameraModel.PINHOLE, width, height, (fx, fy, cx, cy))

    # ---- intrinsics ----------------------------------------------------------------------
    @property
    def focal(self) -> tuple[float, float]:
        """(fx, fy) in pixels."""
        if self.model in _ONE_FOCAL:
            return self.params[0], self.params[0]
        return self.params[0], self.params[1]

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) in pixels."""
        i = self._principal_point_index
        return self.params[i], self.params[i + 1]

    @property
    def _principal_point_index(self) -> int:
        return 1 if self.model in _ONE_FOCAL else 2

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix (distortion not included)."""
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """(4,) OpenCV distortion coefficients ``D`` of the model, for use with ``K``.

        - ``OPENCV``: ``(k1, k2, p1, p2)``; ``RADIAL``: ``(k1, k2, 0, 0)``; ``SIMPLE_RADIAL``:
          ``(k, 0, 0, 0)``; pinhole models: zeros. These are ``distCoeffs`` of
          ``cv2.projectPoints`` / ``cv2.undistortPoints`` (ROS ``plumb_bob`` with ``k3 = 0``).
        - ``OPENCV_FISHEYE``: ``(k1, k2, k3, k4)``, the ``D`` of ``cv2.fisheye.*`` (ROS
          ``equidistant``), **not** radial-tangential coefficients.
        """
        d = np.zeros(4)
        extra = self.params[self._principal_point_index + 2 :]
        d[: len(extra)] = extra
        return d

    @property
    def has_distortion(self) -> bool:
        """True when pixels are not an affine map of ``(x/z, y/z)``: a distortion coefficient
        is non-zero, or the model is ``OPENCV_FISHEYE`` (its equidistant projection bends rays
        even with ``k1 = … = k4 = 0``)."""
        # Plain Python on the few parameters: called per query, where numpy's overhead dominated.
        extra = self.params[self._principal_point_index + 2 :]
        return self.model == CameraModel.OPENCV_FISHEYE or any(p != 0.0 for p in extra)

    def scaled(self, sx: float, sy: float | None = None) -> Camera:
        """The same camera for an image resized by (sx, sy) (as ``cv2.resize`` does).

        With pixel centres on integers (OpenCV), ``u' = s (u + 0.5) - 0.5``. One-focal models
        become their two-focal equivalent (``SIMPLE_PINHOLE`` -> ``PINHOLE``, ``SIMPLE_RADIAL``
        and ``RADIAL`` -> ``OPENCV`` with ``p1 = p2 = 0``); distortion is unchanged."""
        sy = sx if sy is None else sy
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        model = CameraModel(self.model)  # already one (__post_init__); typed for the lookup
        model = _TWO_FOCAL.get(model, model)
        p = (fx * sx, fy * sy, sx * (cx + 0.5) - 0.5, sy * (cy + 0.5) - 0.5)
        if model != CameraModel.PINHOLE:
            p = (*p, *self.distortion)
        return Camera(model, round(self.width * sx), round(self.height * sy), p)

    def with_principal_point_offset(self, dx: float, dy: float) -> Camera:
        """The same camera with ``(cx + dx, cy + dy)``; e.g. ``(-0.5, -0.5)`` converts COLMAP's
        pixel convention (top-left pixel centre at (0.5, 0.5)) to planarloc's (OpenCV)."""
        p = list(self.params)
        i = self._principal_point_index
        p[i] += dx
        p[i + 1] += dy
        return Camera(self.model, self.width, self.height, tuple(p))

    # ---- projection ----------------------------------------------------------------------
    def cam_from_img(self, points: object) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalized coordinates ``(x/z, y/z)`` (N, 2).

        Rows where the distortion has no unique inverse come back NaN: for the radial models
        and ``OPENCV`` beyond the radius where ``r (1 + k1 r² + k2 r⁴)`` stops increasing
        (:func:`max_undistorted_radius`); for ``OPENCV_FISHEYE`` beyond the angle where
        ``θ_d(θ)`` stops increasing (:func:`max_fisheye_angle`), and for rays at 90° or more
        from the optical axis (``z <= 0``), which have no normalized coordinates (use
        :meth:`unit_bearings_from_img`)."""
        uv = check_array("points", points, (None, 2))
        xd = self._distorted_from_img(uv)
        if self.model == CameraModel.OPENCV_FISHEYE:
            theta_d = np.hypot(xd[:, 0], xd[:, 1])
            theta = undistort_fisheye_angle(theta_d, self.distortion)
            theta[theta >= 0.5 * np.pi] = np.nan
            return xd * _ratio(np.tan(theta), theta_d)[:, None]
        if not self.has_distortion:
            return xd
        return undistort_normalized(xd, self.distortion)

    def img_from_cam(self, points: object) -> np.ndarray:
        """Normalized (N, 2) or camera-frame (N, 3) points -> pixels (N, 2), with distortion.

        3D points must be in front of the camera (z > 0), except for ``OPENCV_FISHEYE``, which
        projects any non-zero point by its angle ``θ = atan2(√(x² + y²), z)``. Points beyond the
        model's valid range (:func:`max_undistorted_radius`, :func:`max_fisheye_angle`) come
        back NaN."""
        x = check_array("points", points)
        if x.ndim != 2 or x.shape[1] not in (2, 3):
            raise InputError(f"points: expected shape (N, 2) or (N, 3), got {x.shape}")
        fisheye = self.model == CameraModel.OPENCV_FISHEYE
        if x.shape[1] == 3:
            if fisheye and not np.all(np.einsum("ij,ij->i", x, x) > 0):
                raise InputError("points: 3D points must be non-zero (a direction from the camera centre)")
            if not fisheye and np.any(x[:, 2] <= 0):
                raise InputError("points: 3D points must have z > 0 (in front of the camera)")
        if fisheye:
            X = x if x.shape[1] == 3 else np.hstack([x, np.ones((len(x), 1))])
            r = np.hypot(X[:, 0], X[:, 1])
            theta = np.arctan2(r, X[:, 2])
            x = X[:, :2] * _ratio(distort_fisheye_angle(theta, self.distortion), r, 0.0)[:, None]
            x[theta >= max_fisheye_angle(self.distortion)] = np.nan
        else:
            if x.shape[1] == 3:
                x = x[:, :2] / x[:, 2:3]
            if self.has_distortion:
                r_max = max_undistorted_radius(self.distortion)
                beyond = np.einsum("ij,ij->i", x, x) >= r_max * r_max
                x = distort_normalized(x, self.distortion)
                x[beyond] = np.nan
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([fx * x[:, 0] + cx, fy * x[:, 1] + cy], axis=1)

    def bearings_from_img(self, points: object) -> np.ndarray:
        """Pixels (N, 2) -> homogeneous normalized rays (N, 3) ``(x, y, 1)``.

        Scaled by a z-depth they give camera-frame points. NaN where :meth:`cam_from_img` is
        NaN, which includes fisheye rays at 90° or more from the axis."""
        x = self.cam_from_img(points)
        return np.hstack([x, np.ones((len(x), 1))])

    def unit_bearings_from_img(self, points: object) -> np.ndarray:
        """Pixels (N, 2) -> unit bearing vectors (N, 3) in the camera frame.

        Unlike :meth:`bearings_from_img`, valid for ``OPENCV_FISHEYE`` rays at 90° or more from
        the optical axis, up to :func:`max_fisheye_angle`; NaN beyond it (and, for the other
        models, where :meth:`cam_from_img` is NaN). :meth:`img_from_cam` is the inverse."""
        if self.model != CameraModel.OPENCV_FISHEYE:
            rays = self.bearings_from_img(points)
            return rays / np.linalg.norm(rays, axis=1, keepdims=True)
        xd = self._distorted_from_img(check_array("points", points, (None, 2)))
        theta_d = np.hypot(xd[:, 0], xd[:, 1])
        theta = undistort_fisheye_angle(theta_d, self.distortion)
        return np.hstack([xd * _ratio(np.sin(theta), theta_d)[:, None], np.cos(theta)[:, None]])

    def _distorted_from_img(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) validated pixels -> distorted normalized coordinates ``K⁻¹ (u, v, 1)``."""
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], axis=1)


def _ratio(num: np.ndarray, den: np.ndarray, at_zero: float = 1.0) -> np.ndarray:
    """``num / den`` where ``den > 0``, else ``at_zero`` (the limit on the optical axis)."""
    return np.divide(num, den, out=np.full_like(num, at_zero), where=den > 0)


def _pixel_count(name: str, value: object) -> int:
    """An image width/height: a positive whole number (``640`` or ``640.0``, never ``640.5``)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(
            f"Camera.{name}: image size must be positive whole pixel counts, got {value!r}"
        ) from None
    if isinstance(value, bool) or not np.isfinite(v) or v != int(v) or v <= 0:
        raise InputError(f"Camera.{name}: image size must be positive whole pixel counts, got {value!r}")
    return int(v)


def max_undistorted_radius(dist: object) -> float:
    """Largest normalized radius where OpenCV's radial distortion is still monotonic.

    The radial part maps ``r -> r (1 + k1 r² + k2 r⁴)``; its derivative ``1 + 3 k1 r² + 5 k2 r⁴``
    first vanishes at the returned radius (``inf`` if it never does, e.g. ``k1, k2 >= 0``).
    Beyond it the distortion folds back, so pixels there have no unique ray; like COLMAP,
    planarloc treats them as outside the model (the tangential terms are ignored here).

    Args:
        dist: (4,) ``(k1, k2, p1, p2)``.

    Returns:
        The radius (unitless, in normalized coordinates), > 0 or ``inf``.
    """
    k1, k2 = float(np.asarray(dist, dtype=float)[0]), float(np.asarray(dist, dtype=float)[1])
    # roots in s = r² of a s² + b s + 1 = 0, in the form that does not cancel for tiny k2
    a, b = 5.0 * k2, 3.0 * k1
    if a == 0.0:
        roots = [-1.0 / b] if b != 0.0 else []
    else:
        disc = b * b - 4.0 * a
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b)) if disc >= 0 else 0.0
        roots = [q / a, 1.0 / q] if q != 0.0 else []
    positive = [s for s in roots if s > 0]
    return float(np.sqrt(min(positive))) if positive else float("inf")


def distort_normalized(x: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV radial-tangential distortion ``(k1, k2, p1, p2)`` to (N, 2) normalized points."""
    k1, k2, p1, p2 = dist
    u, v = x[:, 0], x[:, 1]
    r2 = u * u + v * v
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    du = 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u)
    dv = p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v
    return np.stack([u * radial + du, v * radial + dv], axis=1)


def undistort_normalized(xd: np.ndarray, dist: np.ndarray, iterations: int = 30) -> np.ndarray:
    """Invert :func:`distort_normalized` by vectorized Newton iterations.

    Hand-written rather than ``cv2.undistortPoints`` because the geometry layer depends on
    numpy only, and OpenCV's default 5 fixed-point iterations leave errors of 1e-3 at strong
    distortion; Newton converges to machine precision in a few steps.
    """
    k1, k2, p1, p2 = dist
    x = xd.copy()
    for _ in range(iterations):
        u, v = x[:, 0], x[:, 1]
        r2 = u * u + v * v
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        drad = 2.0 * k1 + 4.0 * k2 * r2  # d(radial)/d(r2) * 2
        f = distort_normalized(x, dist) - xd
        # Jacobian of the distortion map, 2x2 per point.
        j00 = radial + u * drad * u + 2.0 * p1 * v + 6.0 * p2 * u
        j01 = u * drad * v + 2.0 * p1 * u + 2.0 * p2 * v
        j10 = v * drad * u + 2.0 * p1 * u + 2.0 * p2 * v
        j11 = radial + v * drad * v + 6.0 * p1 * v + 2.0 * p2 * u
        det = j00 * j11 - j01 * j10
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step_u = (j11 * f[:, 0] - j01 * f[:, 1]) / det
        step_v = (-j10 * f[:, 0] + j00 * f[:, 1]) / det
        x[:, 0] -= step_u
        x[:, 1] -= step_v
        if max(np.abs(step_u).max(initial=0.0), np.abs(step_v).max(initial=0.0)) < 1e-14:
            break
    # Outside the range where the distortion map is invertible Newton converges to a wrong
    # point: mark those NaN rather than return a wrong ray.
    bad = np.abs(distort_normalized(x, dist) - xd).max(axis=1) > 1e-9
    # Beyond the radius where the radial distortion folds back, a converged point is one of
    # two preimages (and the wrong one for pixels in the outer image): outside the model.
    r_max = max_undistorted_radius(dist)
    bad |= np.einsum("ij,ij->i", x, x) >= r_max * r_max
    x[bad] = np.nan
    return x


def max_fisheye_angle(dist: object) -> float:
    """Largest angle from the optical axis where the fisheye's ``θ_d(θ)`` is still increasing.

    ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`` has the derivative
    ``1 + 3 k1 θ² + 5 k2 θ⁴ + 7 k3 θ⁶ + 9 k4 θ⁸``; the returned angle is its first positive
    root, capped at π (a ray's angle from the axis is at most π). Beyond it a pixel radius
    has no or several angles, so planarloc treats those rays as outside the model. The root
    is bracketed by the first sign change on a grid of π/4096 and refined by bisection
    (``np.roots`` loses it when ``k4`` is tiny); a dip below zero narrower than the grid
    step is not seen.

    Args:
        dist: (4,) ``(k1, k2, k3, k4)``.

    Returns:
        The angle in radians, in (0, π].
    """
    d = check_array("dist", dist, (4,))
    grid = np.linspace(0.0, np.pi, 4097)
    falling = np.flatnonzero(_fisheye_slope(grid, d) <= 0)
    if len(falling) == 0:
        return float(np.pi)
    lo, hi = float(grid[falling[0] - 1]), float(grid[falling[0]])  # slope(lo) > 0 >= slope(hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _fisheye_slope(mid, d) > 0 else (lo, mid)
    return lo


def distort_fisheye_angle(theta: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N,) angles θ from the optical axis (radians) -> (N,) distorted radii ``θ_d``
    (normalized units) of the Kannala-Brandt model with ``dist = (k1, k2, k3, k4)``."""
    k1, k2, k3, k4 = dist
    t2 = theta * theta
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def _fisheye_slope(theta: np.ndarray | float, dist: np.ndarray) -> np.ndarray | float:
    """(N,) (or scalar) derivative ``dθ_d / dθ`` of :func:`distort_fisheye_angle`."""
    k1, k2, k3, k4 = dist
    t2 = theta * theta
    return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))


def undistort_fisheye_angle(theta_d: np.ndarray, dist: np.ndarray, iterations: int = 60) -> np.ndarray:
    """Invert :func:`distort_fisheye_angle` on ``[0, max_fisheye_angle)`` (vectorized).

    Newton's method on ``θ_d(θ) - θ_d`` inside a bracket that shrinks with each step; a step
    that leaves the bracket is replaced by bisection, so every point converges.

    Args:
        theta_d: (N,) distorted radii ``‖K⁻¹ (u, v, 1)‖`` (normalized units, >= 0).
        dist: (4,) ``(k1, k2, k3, k4)``.
        iterations: upper bound on the iterations (it stops when every step or residual is
            below 1e-15).

    Returns:
        (N,) angles θ in radians; NaN where ``θ_d`` is at or beyond ``θ_d(max_fisheye_angle)``.
    """
    theta_max = max_fisheye_angle(dist)
    valid = theta_d < distort_fisheye_angle(np.array([theta_max]), dist)[0]
    lo, hi = np.zeros_like(theta_d), np.full_like(theta_d, theta_max)
    theta = np.minimum(theta_d, theta_max)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(iterations):
            f = distort_fisheye_angle(theta, dist) - theta_d
            lo, hi = np.where(f < 0, theta, lo), np.where(f > 0, theta, hi)
            new = theta - f / _fisheye_slope(theta, dist)
            new = np.where((new >= lo) & (new <= hi), new, 0.5 * (lo + hi))
            step = np.abs(new - theta)
            theta = new
            # Done when every step or residual is at rounding level (near the fold, where the
            # slope is small, rounding alone makes steps of a few 1e-16 / slope).
            if not np.any(valid & (step > 1e-15) & (np.abs(f) > 1e-15)):
                break
    # Not converged (at most the few points right at the fold): outside the model, not a guess.
    valid &= np.abs(distort_fisheye_angle(theta, dist) - theta_d) <= 1e-12
    return np.where(valid, theta, np.nan)
