"""Camera models (COLMAP names and parameter order), projection round trips, OpenCV cross-check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planarloc.geometry.camera import (
    NUM_PARAMS,
    UNSUPPORTED_COLMAP_MODELS,
    Camera,
    CameraModel,
    distort_fisheye_angle,
    max_fisheye_angle,
    max_undistorted_radius,
    undistort_fisheye_angle,
)
from planarloc.geometry.validation import InputError

W, H = 640, 480
PARAMS = {
    "SIMPLE_PINHOLE": (500.0, 320.0, 240.0),
    "PINHOLE": (510.0, 490.0, 321.5, 238.25),
    "SIMPLE_RADIAL": (505.0, 321.5, 238.25, -0.12),
    "RADIAL": (505.0, 321.5, 238.25, -0.25, 0.08),
    "OPENCV": (510.0, 490.0, 321.5, 238.25, -0.2, 0.05, 1e-3, -2e-3),
    # A 640x480 fisheye whose corners are 118 degrees off the axis (an Intel T265-like lens).
    "OPENCV_FISHEYE": (190.0, 191.0, 321.5, 238.25, -0.00228, 0.0373, -0.0351, 0.00552),
}
ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
SUPPORTED = "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE"
# The OpenCV distortion vector of each model: distCoeffs of cv2.projectPoints, D of cv2.fisheye.
EXPECTED_DISTORTION = {
    "SIMPLE_PINHOLE": (0.0, 0.0, 0.0, 0.0),
    "PINHOLE": (0.0, 0.0, 0.0, 0.0),
    "SIMPLE_RADIAL": (-0.12, 0.0, 0.0, 0.0),
    "RADIAL": (-0.25, 0.08, 0.0, 0.0),
    "OPENCV": PARAMS["OPENCV"][4:],
    "OPENCV_FISHEYE": PARAMS["OPENCV_FISHEYE"][4:],
}


def pixel_grid(cam: Camera, nu: int = 321, nv: int = 241) -> np.ndarray:
    """(nu * nv, 2) pixels on a grid spanning the whole image, corners included."""
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, nu), np.linspace(-0.5, cam.height - 0.5, nv))
    return np.stack([u.ravel(), v.ravel()], axis=1)


# ---- models and validation --------------------------------------------------------------------


def test_param_counts_follow_colmap() -> None:
    assert {m.value: n for m, n in NUM_PARAMS.items()} == {
        "SIMPLE_PINHOLE": 3,
        "PINHOLE": 4,
        "SIMPLE_RADIAL": 4,
        "RADIAL": 5,
        "OPENCV": 8,
        "OPENCV_FISHEYE": 8,
    }
    assert [m.value for m in Camera.SUPPORTED_MODELS] == SUPPORTED.split(", ")


@pytest.mark.parametrize("model", list(PARAMS))
def test_each_model_builds_and_exposes_intrinsics(model: str) -> None:
    cam = Camera(model, W, H, PARAMS[model])
    assert cam.model == CameraModel(model)
    p = PARAMS[model]
    if model in ONE_FOCAL:
        assert cam.focal == (p[0], p[0]) and cam.principal_point == (p[1], p[2])
    else:
        assert cam.focal == (p[0], p[1]) and cam.principal_point == (p[2], p[3])
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    np.testing.assert_array_equal(cam.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    np.testing.assert_array_equal(cam.distortion, EXPECTED_DISTORTION[model])


@pytest.mark.parametrize("model", list(PARAMS))
def test_has_distortion(model: str) -> None:
    assert Camera(model, W, H, PARAMS[model]).has_distortion == (model not in ("SIMPLE_PINHOLE", "PINHOLE"))
    n_intrinsics = 3 if model in ONE_FOCAL else 4
    zeros = (*PARAMS[model][:n_intrinsics], *[0.0] * (len(PARAMS[model]) - n_intrinsics))
    # All coefficients zero: no distortion, except for the fisheye, whose projection is not a pinhole's.
    assert Camera(model, W, H, zeros).has_distortion == (model == "OPENCV_FISHEYE")
    # One non-zero coefficient, whichever it is, counts.
    for i in range(n_intrinsics, len(zeros)):
        p = list(zeros)
        p[i] = 1e-3
        assert Camera(model, W, H, p).has_distortion


def test_model_name_is_case_insensitive_and_accepts_the_enum() -> None:
    assert Camera("pinhole", W, H, PARAMS["PINHOLE"]).model == CameraModel.PINHOLE
    assert Camera(CameraModel.OPENCV, W, H, PARAMS["OPENCV"]).model == CameraModel.OPENCV


@pytest.mark.parametrize("model", list(PARAMS))
@pytest.mark.parametrize("delta", [-1, 1])
def test_wrong_param_count_is_rejected(model: str, delta: int) -> None:
    p = PARAMS[model]
    bad = p[:-1] if delta < 0 else (*p, 0.0)
    with pytest.raises(InputError, match=f"{model} takes {len(p)} parameters, got {len(bad)}") as exc:
        Camera(model, W, H, bad)
    assert str(exc.value).endswith(f"(expected {', '.join(PARAM_ORDER[model])})")


PARAM_ORDER = {  # COLMAP src/colmap/sensor/models.h, params_info of each model
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}


def test_unknown_model_is_rejected_with_the_supported_list() -> None:
    with pytest.raises(InputError, match=f"unknown model 'KANNALA'; supported: {SUPPORTED}$"):
        Camera("KANNALA", W, H, (1.0, 2.0, 3.0))


@pytest.mark.parametrize(
    "model",
    ["FULL_OPENCV", "THIN_PRISM_FISHEYE", "FOV", "SIMPLE_RADIAL_FISHEYE", "radial_fisheye", "FISHEYE"],
)
def test_unsupported_colmap_model_is_rejected_as_not_supported_yet(model: str) -> None:
    assert model.upper() in UNSUPPORTED_COLMAP_MODELS
    with pytest.raises(
        InputError, match=f"COLMAP model {model.upper()} is not supported yet; supported: {SUPPORTED}$"
    ):
        Camera(model, W, H, (500.0, 500.0, 320.0, 240.0, 0.0))


@pytest.mark.parametrize("size", [(0, 480), (640, 0), (-1, 480), (640.5, 480), (640, 479.9), ("640x", 480)])
def test_bad_image_size_is_rejected(size) -> None:
    with pytest.raises(ValueError, match="image size must be positive"):
        Camera("PINHOLE", *size, PARAMS["PINHOLE"])


@pytest.mark.parametrize(
    ("model", "params"),
    [
        ("SIMPLE_PINHOLE", (0.0, 320.0, 240.0)),
        ("PINHOLE", (500.0, -1.0, 320.0, 240.0)),
        ("SIMPLE_RADIAL", (-5.0, 320.0, 240.0, 0.1)),
        ("OPENCV_FISHEYE", (190.0, 0.0, 320.0, 240.0, 0, 0, 0, 0)),
    ],
)
def test_non_positive_focal_is_rejected(model: str, params) -> None:
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Camera(model, W, H, params)


def test_one_focal_models_take_cx_second() -> None:
    # A principal point at the image edge is unusual but valid: not mistaken for a focal length.
    assert Camera("RADIAL", W, H, (500.0, 0.0, -1.0, 0.1, 0.0)).principal_point == (0.0, -1.0)


def test_non_finite_params_are_rejected() -> None:
    with pytest.raises(InputError, match="NaN or inf"):
        Camera("PINHOLE", W, H, (500.0, np.nan, 320.0, 240.0))


def test_bad_point_shapes_are_rejected() -> None:
    cam = Camera("PINHOLE", W, H, PARAMS["PINHOLE"])
    with pytest.raises(ValueError, match=r"expected shape \(N, 2\)"):
        cam.cam_from_img(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"expected shape \(N, 2\) or \(N, 3\)"):
        cam.img_from_cam(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="z > 0"):
        cam.img_from_cam(np.array([[0.0, 0.0, -1.0]]))


# ---- projection -------------------------------------------------------------------------------


def test_principal_point_maps_to_the_optical_axis() -> None:
    cam = Camera("PINHOLE", W, H, PARAMS["PINHOLE"])
    np.testing.assert_array_equal(cam.cam_from_img([cam.principal_point]), [[0.0, 0.0]])
    np.testing.assert_array_equal(cam.bearings_from_img([cam.principal_point]), [[0.0, 0.0, 1.0]])
    # x right, y down: a pixel right of and below the principal point has x > 0 and y > 0.
    x = cam.cam_from_img([[cam.principal_point[0] + 10.0, cam.principal_point[1] + 10.0]])
    assert x[0, 0] > 0 and x[0, 1] > 0


@st.composite
def opencv_cameras(draw) -> Camera:
    # Distortion invertible for r² <= 0.6: 1 + 3 k1 r² + 5 k2 r⁴ > 0 for these coefficients.
    f = draw(st.floats(300.0, 1500.0))
    aspect = draw(st.floats(0.9, 1.1))
    cx = draw(st.floats(0.4 * W, 0.6 * W))
    cy = draw(st.floats(0.4 * H, 0.6 * H))
    k1 = draw(st.floats(-0.25, 0.25))
    k2 = draw(st.floats(-0.05, 0.05))
    p1 = draw(st.floats(-2e-3, 2e-3))
    p2 = draw(st.floats(-2e-3, 2e-3))
    return Camera("OPENCV", W, H, (f, f * aspect, cx, cy, k1, k2, p1, p2))


@settings(max_examples=40, deadline=None)
@given(opencv_cameras(), st.integers(0, 2**31 - 1))
def test_opencv_round_trips_below_1e9(cam: Camera, seed: int) -> None:
    """Round trips over the field of view where the distortion map is invertible.

    Points are drawn in undistorted normalized coordinates (|x| <= 0.6, |y| <= 0.45) and
    projected: a pixel drawn at random could lie outside the range of the distortion map
    (strong barrel distortion folds over), where no undistorted point exists.
    """
    rng = np.random.default_rng(seed)
    x = rng.uniform([-0.6, -0.45], [0.6, 0.45], (50, 2))
    uv = cam.img_from_cam(x)
    np.testing.assert_allclose(cam.cam_from_img(uv), x, atol=1e-9, rtol=0)
    np.testing.assert_allclose(cam.img_from_cam(cam.cam_from_img(uv)), uv, atol=1e-9, rtol=0)
    # 3D input: the same as its normalized coordinates.
    X = np.hstack([x, np.ones((len(x), 1))]) * rng.uniform(0.5, 20.0, (len(x), 1))
    np.testing.assert_allclose(cam.img_from_cam(X), uv, atol=1e-9, rtol=0)


@settings(max_examples=30, deadline=None)
@given(opencv_cameras(), st.integers(0, 2**31 - 1))
def test_opencv_distortion_matches_cv2_project_points(cam: Camera, seed: int) -> None:
    """Peer check: OpenCV's projectPoints with dist = (k1, k2, p1, p2) gives the same pixels."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-0.5, 0.5, (40, 2)), np.ones(40)] * rng.uniform(1.0, 10.0, (40, 1))
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.distortion)
    np.testing.assert_allclose(cam.img_from_cam(X), ref.reshape(-1, 2), atol=1e-8, rtol=0)
    # and OpenCV's iterative undistortion (many iterations) agrees with our Newton inverse
    uv = cam.img_from_cam(X)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.distortion, criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(cam.cam_from_img(uv), und, atol=1e-7, rtol=0)


@settings(max_examples=30, deadline=None)
@given(st.sampled_from(["SIMPLE_PINHOLE", "PINHOLE"]), st.integers(0, 2**31 - 1))
def test_pinhole_round_trip_is_exact(model: str, seed: int) -> None:
    cam = Camera(model, W, H, PARAMS[model])
    uv = np.random.default_rng(seed).uniform([0, 0], [W, H], (20, 2))
    x = cam.cam_from_img(uv)
    np.testing.assert_allclose(x, (uv - cam.principal_point) / np.array(cam.focal), atol=1e-15)
    np.testing.assert_allclose(cam.img_from_cam(x), uv, atol=1e-12)


def test_opencv_with_zero_distortion_equals_pinhole() -> None:
    pin = Camera("PINHOLE", W, H, PARAMS["PINHOLE"])
    ocv = Camera("OPENCV", W, H, (*PARAMS["PINHOLE"], 0.0, 0.0, 0.0, 0.0))
    uv = np.random.default_rng(0).uniform([0, 0], [W, H], (20, 2))
    np.testing.assert_array_equal(ocv.cam_from_img(uv), pin.cam_from_img(uv))
    x = pin.cam_from_img(uv)
    np.testing.assert_array_equal(ocv.img_from_cam(x), pin.img_from_cam(x))


# ---- from_K and scaled ------------------------------------------------------------------------


def test_from_K() -> None:
    K = np.array([[510.0, 0.0, 321.5], [0.0, 490.0, 238.25], [0.0, 0.0, 1.0]])
    cam = Camera.from_K(K, W, H)
    assert cam.model == CameraModel.PINHOLE and cam.params == PARAMS["PINHOLE"]
    np.testing.assert_array_equal(cam.K, K)
    assert Camera.from_K(K, W, H, dist=np.zeros(4)).model == CameraModel.PINHOLE
    cam = Camera.from_K(K, W, H, dist=PARAMS["OPENCV"][4:])
    assert cam.model == CameraModel.OPENCV and cam.params == PARAMS["OPENCV"]
    with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\)"):
        Camera.from_K(np.eye(4), W, H)
    with pytest.raises(ValueError, match=r"dist: expected shape \(4,\), got \(5,\)"):
        Camera.from_K(K, W, H, dist=[0.1, 0.0, 0.0, 0.0, 0.01])


@pytest.mark.parametrize("model", list(PARAMS))
@pytest.mark.parametrize(("sx", "sy"), [(0.5, None), (2.0, None), (0.5, 0.25)])
def test_scaled_keeps_model_family_distortion_and_scales_focal_and_size(model: str, sx: float, sy) -> None:
    cam = Camera(model, W, H, PARAMS[model])
    s = cam.scaled(sx, sy)
    sy_ = sx if sy is None else sy
    assert (s.width, s.height) == (round(W * sx), round(H * sy_))
    np.testing.assert_allclose(s.focal, (cam.focal[0] * sx, cam.focal[1] * sy_))
    np.testing.assert_array_equal(s.distortion, cam.distortion)
    # One-focal models become their two-focal equivalent, which may have fx != fy.
    expected = {"SIMPLE_PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV"}.get(model, model)
    assert s.model == CameraModel(expected)
    # The same ray projects to the scaled pixel up to the half-pixel offset of the
    # principal point (see the test below).
    x = np.array([[0.1, -0.05], [-0.2, 0.15]])
    np.testing.assert_allclose(s.img_from_cam(x), cam.img_from_cam(x) * [sx, sy_], atol=1.0)


def test_scaled_principal_point_follows_the_opencv_pixel_convention() -> None:
    cam = Camera("PINHOLE", W, H, PARAMS["PINHOLE"])
    # cv2.resize maps pixel centres u -> s (u + 0.5) - 0.5: check it on a blob first.
    u0, v0, s = 301.3, 157.8, 0.5
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    img = np.exp(-((jj - u0) ** 2 + (ii - v0) ** 2) / (2 * 6.0**2))
    small = cv2.resize(img, (round(W * s), round(H * s)), interpolation=cv2.INTER_AREA)
    j2, i2 = np.meshgrid(np.arange(small.shape[1]), np.arange(small.shape[0]))
    centroid = ((small * j2).sum() / small.sum(), (small * i2).sum() / small.sum())
    np.testing.assert_allclose(centroid, (s * (u0 + 0.5) - 0.5, s * (v0 + 0.5) - 0.5), atol=1e-3)
    cx, cy = cam.principal_point
    np.testing.assert_allclose(cam.scaled(s).principal_point, (s * (cx + 0.5) - 0.5, s * (cy + 0.5) - 0.5))


def test_whole_float_sizes_are_accepted_as_ints() -> None:
    cam = Camera("PINHOLE", 640.0, "480", PARAMS["PINHOLE"])
    assert (cam.width, cam.height) == (640, 480) and isinstance(cam.width, int)


@pytest.mark.parametrize(
    "cam",
    [
        Camera("OPENCV", 1241, 376, (718.856, 718.856, 607.19, 185.22, -0.3, 0.0, 0.0, 0.0)),
        Camera("SIMPLE_RADIAL", 1241, 376, (718.856, 607.19, 185.22, -0.3)),
        Camera("RADIAL", 1241, 376, (718.856, 607.19, 185.22, -0.3, 0.0)),
    ],
    ids=["OPENCV", "SIMPLE_RADIAL", "RADIAL"],
)
def test_pixels_beyond_the_radial_fold_are_nan(cam: Camera) -> None:
    """k1 = -0.3 folds back at r = 1/sqrt(0.9): pixels beyond map to NaN, never to the opposite quadrant."""
    r_max = max_undistorted_radius(cam.distortion)
    assert r_max == pytest.approx(1.0 / np.sqrt(0.9))
    u, v = np.meshgrid(np.linspace(0, 1240, 80), np.linspace(0, 375, 68))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    x = cam.cam_from_img(uv)
    ok = np.isfinite(x).all(axis=1)
    xd = (uv - cam.principal_point) / cam.focal
    assert 0 < ok.sum() < len(uv)
    assert np.all(np.sign(x[ok]) == np.sign(xd[ok]))  # same quadrant as the distorted point
    assert np.all(np.hypot(*x[ok].T) < r_max)
    assert np.isnan(cam.cam_from_img([[0.0, 0.0]])).all()
    np.testing.assert_allclose(cam.img_from_cam(x[ok]), uv[ok], atol=1e-6)  # valid points round-trip
    assert np.isnan(cam.img_from_cam([[1.2, 0.0]])).all()  # beyond the fold: no pixel


@pytest.mark.parametrize(
    ("k1", "k2", "expected"),
    [
        (0.1, 0.01, np.inf),
        (0.0, 0.0, np.inf),
        (-0.3, 0.0, 1.0 / np.sqrt(0.9)),
        (0.0, -0.1, 2.0**0.25),
        (-0.3, 1e-20, 1.0 / np.sqrt(0.9)),
        (-0.3, -1e-20, 1.0 / np.sqrt(0.9)),
        (0.3, 1e-20, np.inf),
    ],
)
def test_max_undistorted_radius(k1: float, k2: float, expected: float) -> None:
    r = max_undistorted_radius([k1, k2, 0.0, 0.0])
    assert r == pytest.approx(expected)
    if np.isfinite(r):  # the derivative of the radial map vanishes there
        assert 1 + 3 * k1 * r**2 + 5 * k2 * r**4 == pytest.approx(0.0, abs=1e-12)


def test_with_principal_point_offset_shifts_cx_cy_of_every_model() -> None:
    for model, p in PARAMS.items():
        cam = Camera(model, W, H, p).with_principal_point_offset(-0.5, 0.25)
        assert cam.model == CameraModel(model) and cam.focal == Camera(model, W, H, p).focal
        i = 1 if model in ONE_FOCAL else 2
        assert cam.params == (*p[:i], p[i] - 0.5, p[i + 1] + 0.25, *p[i + 2 :])


# ---- radial and fisheye models ----------------------------------------------------------------


@pytest.mark.parametrize("model", list(PARAMS))
def test_full_image_round_trip_below_1e6_px(model: str) -> None:
    """Every pixel of a dense grid over the whole image: pixel -> cam_from_img -> img_from_cam."""
    cam = Camera(model, W, H, PARAMS[model])
    uv = pixel_grid(cam)
    x = cam.cam_from_img(uv)
    ok = np.isfinite(x).all(axis=1)
    if model == "OPENCV_FISHEYE":  # NaN exactly for the rays at >= 90 degrees (corners of this lens)
        behind = cam.unit_bearings_from_img(uv)[:, 2] <= 0
        assert 0 < behind.sum() < len(uv) // 2
        np.testing.assert_array_equal(ok, ~behind)
    else:
        assert ok.all()
    assert np.abs(cam.img_from_cam(x[ok]) - uv[ok]).max() < 1e-6
    assert np.abs(cam.img_from_cam(np.hstack([x[ok], np.ones((ok.sum(), 1))]) * 3.0) - uv[ok]).max() < 1e-6


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE"])
def test_normalized_points_round_trip(model: str) -> None:
    """The other way: normalized points over the field of view -> pixels -> normalized points."""
    cam = Camera(model, W, H, PARAMS[model])
    rng = np.random.default_rng(1)
    if model == "OPENCV_FISHEYE":  # angles up to 89 degrees: |x| up to 57
        theta, phi = np.radians(rng.uniform(0, 89, 4000)), rng.uniform(-np.pi, np.pi, 4000)
        x = np.tan(theta)[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    else:
        x = rng.uniform([-0.7, -0.55], [0.7, 0.55], (4000, 2))
    uv = cam.img_from_cam(x)
    assert np.isfinite(uv).all()
    np.testing.assert_allclose(cam.cam_from_img(uv), x, rtol=1e-9, atol=1e-12)


def test_fisheye_unit_bearings_round_trip_beyond_90_degrees() -> None:
    cam = Camera("OPENCV_FISHEYE", W, H, PARAMS["OPENCV_FISHEYE"])
    uv = pixel_grid(cam)
    b = cam.unit_bearings_from_img(uv)
    assert np.isfinite(b).all()
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-15)
    assert np.degrees(np.arccos(b[:, 2].min())) > 115  # the corners look backwards
    assert np.abs(cam.img_from_cam(b) - uv).max() < 1e-6
    # ... and from random directions of the sphere within the image's angles to pixels and back
    rng = np.random.default_rng(2)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > -0.4]  # up to 113 degrees off the axis
    np.testing.assert_allclose(cam.unit_bearings_from_img(cam.img_from_cam(d * 2.5)), d, atol=1e-12)
    # In front of the image plane, the homogeneous rays of bearings_from_img are the same directions.
    front = b[:, 2] > 1e-3
    rays = cam.bearings_from_img(uv[front])
    np.testing.assert_allclose(rays / np.linalg.norm(rays, axis=1, keepdims=True), b[front], atol=1e-12)
    assert np.isnan(cam.bearings_from_img(uv[~(b[:, 2] > 0)])[:, :2]).all()


def test_fisheye_projects_points_behind_the_image_plane_by_their_angle() -> None:
    cam = Camera("OPENCV_FISHEYE", W, H, (200.0, 210.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0))
    # Equidistant with k = 0: the radius in normalized units is the angle; x right, y down.
    np.testing.assert_allclose(
        cam.img_from_cam([[1.0, 0.0, -1.0], [0.0, -2.0, 0.0], [0.0, 0.0, 5.0]]),
        [[320.0 + 200.0 * 0.75 * np.pi, 240.0], [320.0, 240.0 - 210.0 * 0.5 * np.pi], [320.0, 240.0]],
        atol=1e-12,
    )
    assert np.isnan(cam.img_from_cam([[0.0, 0.0, -1.0]])).all()  # 180 degrees: no pixel
    with pytest.raises(InputError, match="non-zero"):
        cam.img_from_cam([[0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="z > 0"):  # the other models keep their contract
        Camera("RADIAL", W, H, PARAMS["RADIAL"]).img_from_cam([[1.0, 0.0, -1.0]])


def test_fisheye_beyond_the_fold_is_nan() -> None:
    """k1 = -0.1: θ_d = θ - 0.1 θ³ peaks at θ = 1/sqrt(0.3) (104.6 degrees)."""
    cam = Camera("OPENCV_FISHEYE", W, H, (150.0, 150.0, 320.0, 240.0, -0.1, 0.0, 0.0, 0.0))
    theta_max = max_fisheye_angle(cam.distortion)
    assert theta_max == pytest.approx(1.0 / np.sqrt(0.3))
    uv = pixel_grid(cam)
    radius = np.hypot(*((uv - cam.principal_point) / cam.focal).T)
    b = cam.unit_bearings_from_img(uv)
    ok = np.isfinite(b).all(axis=1)
    peak = theta_max * (1 - 0.1 * theta_max**2)
    np.testing.assert_array_equal(ok, radius < peak)
    assert 0 < ok.sum() < len(uv)
    assert np.all(np.arccos(b[ok, 2]) < theta_max)
    assert np.abs(cam.img_from_cam(b[ok]) - uv[ok]).max() < 1e-6
    angles = np.array([theta_max - 1e-3, theta_max + 1e-3, 3.0])
    dirs = np.stack([np.sin(angles), np.zeros(3), np.cos(angles)], axis=1)
    assert np.isfinite(cam.img_from_cam(dirs)).tolist() == [[True, True], [False, False], [False, False]]


@pytest.mark.parametrize(
    ("dist", "expected"),
    [
        ((0.0, 0.0, 0.0, 0.0), np.pi),
        ((0.05, 0.01, 0.0, 0.0), np.pi),
        ((-0.1, 0.0, 0.0, 0.0), 1.0 / np.sqrt(0.3)),
        ((0.0, 0.0, 0.0, -0.01), (1.0 / 0.09) ** 0.125),
        ((0.02, -0.01, 0.002, -0.001), None),
        ((0.0, -0.03125, 0.0, 1e-68), np.sqrt(np.sqrt(1.0 / 0.15625))),
    ],
)
def test_max_fisheye_angle(dist, expected) -> None:
    theta = max_fisheye_angle(dist)
    if expected is not None:
        assert theta == pytest.approx(expected)
    if theta < np.pi:  # the derivative of θ_d(θ) vanishes there, and is positive before
        k1, k2, k3, k4 = dist
        slope = [
            1 + 3 * k1 * t**2 + 5 * k2 * t**4 + 7 * k3 * t**6 + 9 * k4 * t**8 for t in (theta, 0.99 * theta)
        ]
        assert slope[0] == pytest.approx(0.0, abs=1e-12) and slope[1] > 0


@st.composite
def radial_cameras(draw) -> Camera:
    # 1 + 3 k1 r² + 5 k2 r⁴ > 0 on the field of view for these coefficients (no fold).
    f = draw(st.floats(300.0, 1500.0))
    cx, cy = draw(st.floats(0.4 * W, 0.6 * W)), draw(st.floats(0.4 * H, 0.6 * H))
    k1, k2 = draw(st.floats(-0.25, 0.25)), draw(st.floats(-0.05, 0.05))
    if draw(st.booleans()):
        return Camera("SIMPLE_RADIAL", W, H, (f, cx, cy, k1))
    return Camera("RADIAL", W, H, (f, cx, cy, k1, k2))


@settings(max_examples=30, deadline=None)
@given(radial_cameras(), st.integers(0, 2**31 - 1))
def test_radial_models_match_cv2_with_k1_k2(cam: Camera, seed: int) -> None:
    """Peer check: COLMAP's RADIAL is OpenCV's model with p1 = p2 = 0, distCoeffs (k1, k2, 0, 0)."""
    k = cam.params[3:]
    np.testing.assert_array_equal(cam.distortion, (k[0], k[1] if len(k) > 1 else 0.0, 0.0, 0.0))
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-0.6, 0.6, (40, 2)), np.ones(40)] * rng.uniform(1.0, 10.0, (40, 1))
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, np.array([*k, 0.0, 0.0, 0.0][:4]))
    uv = cam.img_from_cam(X)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-8, rtol=0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.distortion, criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(cam.cam_from_img(uv), und, atol=1e-7, rtol=0)


@st.composite
def fisheye_cameras(draw) -> Camera:
    f = draw(st.floats(150.0, 600.0))
    aspect = draw(st.floats(0.95, 1.05))
    cx, cy = draw(st.floats(0.4 * W, 0.6 * W)), draw(st.floats(0.4 * H, 0.6 * H))
    k = [draw(st.floats(-b, b)) for b in (0.05, 0.05, 0.02, 0.005)]
    return Camera("OPENCV_FISHEYE", W, H, (f, f * aspect, cx, cy, *k))


@settings(max_examples=30, deadline=None)
@given(fisheye_cameras(), st.integers(0, 2**31 - 1))
def test_fisheye_matches_cv2_fisheye(cam: Camera, seed: int) -> None:
    """Peer check: OPENCV_FISHEYE is cv2.fisheye with K and D = (k1, k2, k3, k4)."""
    np.testing.assert_array_equal(cam.distortion, cam.params[4:])
    rng = np.random.default_rng(seed)
    top = min(np.radians(80.0), 0.95 * max_fisheye_angle(cam.distortion))
    theta, phi = rng.uniform(0, top, 40), rng.uniform(-np.pi, np.pi, 40)
    x = np.tan(theta)[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    ref = cv2.fisheye.distortPoints(x.reshape(-1, 1, 2), cam.K, cam.distortion).reshape(-1, 2)
    uv = cam.img_from_cam(x)
    np.testing.assert_allclose(uv, ref, atol=1e-8, rtol=0)
    X = np.c_[x, np.ones(len(x))] * rng.uniform(1.0, 10.0, (len(x), 1))
    ref3, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.distortion)
    np.testing.assert_allclose(cam.img_from_cam(X), ref3.reshape(-1, 2), atol=1e-8, rtol=0)
    np.testing.assert_allclose(cam.cam_from_img(uv), x, rtol=1e-9, atol=1e-12)
    # cv2.fisheye.undistortPoints clamps θ_d to π/2, so it is only comparable below that radius.
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.distortion, criteria=crit).reshape(
        -1, 2
    )
    below = np.hypot(*((uv - cam.principal_point) / cam.focal).T) < 0.5 * np.pi
    # OpenCV marks points its iteration gave up on with -1e6; ours must still invert them (above).
    compared = below & (np.abs(und) < 1e5).all(axis=1)
    np.testing.assert_allclose(cam.cam_from_img(uv[compared]), und[compared], rtol=1e-9, atol=1e-9)


def test_fisheye_angle_inversion_reports_non_convergence_as_nan() -> None:
    d = np.array(PARAMS["OPENCV_FISHEYE"][4:])
    theta = np.linspace(0.0, 2.0, 201)
    theta_d = distort_fisheye_angle(theta, d)
    np.testing.assert_allclose(undistort_fisheye_angle(theta_d, d), theta, atol=1e-12)
    # Too few iterations: the points that have not converged are NaN, never a wrong angle.
    rough = undistort_fisheye_angle(theta_d, d, iterations=1)
    ok = np.isfinite(rough)
    assert 0 < ok.sum() < len(theta)
    np.testing.assert_allclose(rough[ok], theta[ok], atol=1e-10)
