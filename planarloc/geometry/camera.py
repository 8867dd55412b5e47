"""Camera models with COLMAP's names and parameter order (``doc/cameras.rst`` of COLMAP).

=================  ==========================================
model              params
=================  ==========================================
``SIMPLE_PINHOLE`` ``f, cx, cy``
``PINHOLE``        ``fx, fy, cx, cy``
``OPENCV``         ``fx, fy, cx, cy, k1, k2, p1, p2``
=================  ==========================================

Pixel coordinates follow COLMAP/OpenCV: the centre of the top-left pixel is (0.5, 0.5) in
COLMAP and (0, 0) in OpenCV; planarloc uses the **OpenCV** convention, like the intrinsics
users calibrate with OpenCV, KITTI and TUM. ``cam_from_img`` maps pixels to undistorted
normalized coordinates ``(x/z, y/z)``; ``img_from_cam`` is its inverse.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from planarloc.geometry.validation import InputError, check_array


class CameraModel(str, Enum):
    SIMPLE_PINHOLE = "SIMPLE_PINHOLE"
    PINHOLE = "PINHOLE"
    OPENCV = "OPENCV"


NUM_PARAMS = {CameraModel.SIMPLE_PINHOLE: 3, CameraModel.PINHOLE: 4, CameraModel.OPENCV: 8}


@dataclass(frozen=True)
class Camera:
    """An intrinsic camera model.

    Attributes:
        model: a :class:`CameraModel` name, e.g. ``"PINHOLE"``.
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

    def __post_init__(self) -> None:
        try:
            model = CameraModel(str(getattr(self.model, "value", self.model)).upper())
        except ValueError:
            names = ", ".join(m.value for m in CameraModel)
            raise InputError(f"Camera.model: unknown model {self.model!r}; supported: {names}") from None
        params = tuple(float(p) for p in check_array("Camera.params", self.params, (None,)))
        if len(params) != NUM_PARAMS[model]:
            raise InputError(
                f"Camera.params: {model.value} takes {NUM_PARAMS[model]} parameters, got {len(params)}"
            )
        width, height = _pixel_count("width", self.width), _pixel_count("height", self.height)
        if params[0] <= 0 or (model != CameraModel.SIMPLE_PINHOLE and params[1] <= 0):
            raise InputError(f"Camera.params: focal lengths must be positive, got {params[:2]}")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

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
        if self.model == CameraModel.SIMPLE_PINHOLE:
            return self.params[0], self.params[0]
        return self.params[0], self.params[1]

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) in pixels."""
        return (self.params[1], self.params[2]) if self.model == CameraModel.SIMPLE_PINHOLE else (
            self.params[2], self.params[3])

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix (distortion not included)."""
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """(4,) OpenCV ``(k1, k2, p1, p2)``; zeros for pinhole models."""
        return np.array(self.params[4:8]) if self.model == CameraModel.OPENCV else np.zeros(4)

    def scaled(self, sx: float, sy: float | None = None) -> Camera:
        """The same camera for an image resized by (sx, sy) (as ``cv2.resize`` does).

        With pixel centres on integers (OpenCV), ``u' = s (u + 0.5) - 0.5``."""
        sy = sx if sy is None else sy
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        p = (fx * sx, fy * sy, sx * (cx + 0.5) - 0.5, sy * (cy + 0.5) - 0.5, *self.params[4:8])
        model = CameraModel.OPENCV if self.model == CameraModel.OPENCV else CameraModel.PINHOLE
        return Camera(model, round(self.width * sx), round(self.height * sy), p)

    def with_principal_point_offset(self, dx: float, dy: float) -> Camera:
        """The same camera with ``(cx + dx, cy + dy)``; e.g. ``(-0.5, -0.5)`` converts COLMAP's
        pixel convention (top-left pixel centre at (0.5, 0.5)) to planarloc's (OpenCV)."""
        p = list(self.params)
        i = 1 if self.model == CameraModel.SIMPLE_PINHOLE else 2
        p[i] += dx
        p[i + 1] += dy
        return Camera(self.model, self.width, self.height, tuple(p))

    # ---- projection ----------------------------------------------------------------------
    def cam_from_img(self, points: object) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalized coordinates (N, 2).

        Rows outside the valid range of the OPENCV distortion model come back NaN: where the
        radial distortion ``r (1 + k1 r² + k2 r⁴)`` stops increasing with ``r`` (see
        :func:`max_undistorted_radius`), pixels beyond the fold have no or two preimages."""
        uv = check_array("points", points, (None, 2))
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        xd = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], axis=1)
        if self.model != CameraModel.OPENCV or not np.any(self.distortion):
            return xd
        return undistort_normalized(xd, self.distortion)

    def img_from_cam(self, points: object) -> np.ndarray:
        """Normalized (N, 2) or camera-frame (N, 3) points -> pixels (N, 2), with distortion.

        3D points must be in front of the camera (z > 0). Points beyond the OPENCV model's
        valid radius (:func:`max_undistorted_radius`) come back NaN."""
        x = check_array("points", points)
        if x.ndim != 2 or x.shape[1] not in (2, 3):
            raise InputError(f"points: expected shape (N, 2) or (N, 3), got {x.shape}")
        if x.shape[1] == 3:
            if np.any(x[:, 2] <= 0):
                raise InputError("points: 3D points must have z > 0 (in front of the camera)")
            x = x[:, :2] / x[:, 2:3]
        if self.model == CameraModel.OPENCV:
            r_max = max_undistorted_radius(self.distortion)
            beyond = np.einsum("ij,ij->i", x, x) >= r_max * r_max
            x = distort_normalized(x, self.distortion)
            x[beyond] = np.nan
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([fx * x[:, 0] + cx, fy * x[:, 1] + cy], axis=1)

    def bearings_from_img(self, points: object) -> np.ndarray:
        """Pixels (N, 2) -> homogeneous normalized rays (N, 3) ``(x, y, 1)``."""
        x = self.cam_from_img(points)
        return np.hstack([x, np.ones((len(x), 1))])


def _pixel_count(name: str, value: object) -> int:
    """An image width/height: a positive whole number (``640`` or ``640.0``, never ``640.5``)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"Camera.{name}: image size must be positive whole pixel counts, got {value!r}") from None
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
    # roots in s = r² of 5 k2 s² + 3 k1 s + 1 = 0
    if k2 == 0.0:
        roots = [-1.0 / (3.0 * k1)] if k1 != 0.0 else []
    else:
        disc = 9.0 * k1 * k1 - 20.0 * k2
        roots = [] if disc < 0 else [(-3.0 * k1 + sgn * np.sqrt(disc)) / (10.0 * k2) for sgn in (-1.0, 1.0)]
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
