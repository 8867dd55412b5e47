"""Camera models (COLMAP names and parameter order), projection round trips, OpenCV cross-check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planarloc.geometry.camera import NUM_PARAMS, Camera, CameraModel, max_undistorted_radius
from planarloc.geometry.validation import InputError

W, H = 640, 480
PARAMS = {
    "SIMPLE_PINHOLE": (500.0, 320.0, 240.0),
    "PINHOLE": (510.0, 490.0, 321.5, 238.25),
    "OPENCV": (510.0, 490.0, 321.5, 238.25, -0.2, 0.05, 1e-3, -2e-3),
}


# ---- models and validation --------------------------------------------------------------------


def test_param_counts_follow_colmap() -> None:
    assert {m.value: n for m, n in NUM_PARAMS.items()} == {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 8}


@pytest.mark.parametrize("model", list(PARAMS))
def test_each_model_builds_and_exposes_intrinsics(model: str) -> None:
    cam = Camera(model, W, H, PARAMS[model])
    assert cam.model == CameraModel(model)
    p = PARAMS[model]
    if model == "SIMPLE_PINHOLE":
        assert cam.focal == (p[0], p[0]) and cam.principal_point == (p[1], p[2])
    else:
        assert cam.focal == (p[0], p[1]) and cam.principal_point == (p[2], p[3])
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    np.testing.assert_array_equal(cam.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    expected_dist = p[4:8] if model == "OPENCV" else (0.0, 0.0, 0.0, 0.0)
    np.testing.assert_array_equal(cam.distortion, expected_dist)


def test_model_name_is_case_insensitive_and_accepts_the_enum() -> None:
    assert Camera("pinhole", W, H, PARAMS["PINHOLE"]).model == CameraModel.PINHOLE
    assert Camera(CameraModel.OPENCV, W, H, PARAMS["OPENCV"]).model == CameraModel.OPENCV


@pytest.mark.parametrize("model", list(PARAMS))
@pytest.mark.parametrize("delta", [-1, 1])
def test_wrong_param_count_is_rejected(model: str, delta: int) -> None:
    p = PARAMS[model]
    bad = p[:-1] if delta < 0 else (*p, 0.0)
    with pytest.raises(ValueError, match=f"{model} takes {len(p)} parameters, got {len(bad)}"):
        Camera(model, W, H, bad)


def test_unknown_model_is_rejected_with_the_supported_list() -> None:
    with pytest.raises(ValueError, match="unknown model 'FISHEYE'.*SIMPLE_PINHOLE, PINHOLE, OPENCV"):
        Camera("FISHEYE", W, H, (1.0, 2.0, 3.0))


@pytest.mark.parametrize("size", [(0, 480), (640, 0), (-1, 480), (640.5, 480), (640, 479.9), ("640x", 480)])
def test_bad_image_size_is_rejected(size) -> None:
    with pytest.raises(ValueError, match="image size must be positive"):
        Camera("PINHOLE", *size, PARAMS["PINHOLE"])


@pytest.mark.parametrize(
    ("model", "params"),
    [("SIMPLE_PINHOLE", (0.0, 320.0, 240.0)), ("PINHOLE", (500.0, -1.0, 320.0, 240.0))],
)
def test_non_positive_focal_is_rejected(model: str, params) -> None:
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Camera(model, W, H, params)


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
    assert s.model == (CameraModel.OPENCV if model == "OPENCV" else CameraModel.PINHOLE)
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


def test_opencv_pixels_beyond_the_radial_fold_are_nan() -> None:
    """k1 = -0.3 folds back at r = 1/sqrt(0.9): pixels beyond map to NaN, never to the opposite quadrant."""
    cam = Camera("OPENCV", 1241, 376, (718.856, 718.856, 607.19, 185.22, -0.3, 0.0, 0.0, 0.0))
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


@pytest.mark.parametrize(("k1", "k2", "expected"), [(0.1, 0.01, np.inf), (0.0, 0.0, np.inf), (-0.3, 0.0, 1.0 / np.sqrt(0.9)),
                                                    (0.0, -0.1, 2.0 ** 0.25)])
def test_max_undistorted_radius(k1: float, k2: float, expected: float) -> None:
    r = max_undistorted_radius([k1, k2, 0.0, 0.0])
    assert r == pytest.approx(expected)
    if np.isfinite(r):  # the derivative of the radial map vanishes there
        assert 1 + 3 * k1 * r**2 + 5 * k2 * r**4 == pytest.approx(0.0, abs=1e-12)
