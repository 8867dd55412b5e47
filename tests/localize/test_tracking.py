"""Frame-to-frame tracking: corners, Lucas-Kanade tracks, relative pose and its covariance on a
rendered stream, poses from tracked world points, the frame history."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from textured_images import textured_image

from planarloc.features.images import read_gray
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.tracking import (
    FrameHistory,
    FrameTracker,
    Tracked,
    TrackedPoints,
    TrackerOptions,
    detect_corners,
    direction_basis,
    is_blank,
    points_pose_covariance,
    pose_from_points,
    track_checked,
    track_points,
    track_through,
    view_broken,
)
from planarloc.robust.pose_graph import so3_exp
from planarloc.robust.relative_pose import RelativePoseEstimate
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk


@pytest.fixture(scope="module")
def dense_stream(tmp_path_factory: pytest.TempPathFactory) -> list:
    """office at 320x240, 40 query frames ~0.26 m and ~7° apart (a camera-rate stream)."""
    root = generate(
        shrunk(get_preset("office"), scale=0.5, n_map=12, n_query=40),
        tmp_path_factory.mktemp("dense") / "office",
        seed=0,
    )
    return read_dataset(root / "query", "tum")


def test_corners_spread_over_the_image() -> None:
    img = textured_image(np.random.default_rng(0), 240, 480)
    c = detect_corners(img, 120)
    assert 60 <= len(c) <= 120 and c.dtype == np.float32
    counts, _, _ = np.histogram2d(c[:, 0], c[:, 1], bins=(4, 2), range=((0, 480), (0, 240)))
    assert counts.min() >= 5  # every quarter-half of the image has its share
    assert len(detect_corners(np.full((100, 100), 128, np.uint8), 50)) == 0


def test_a_shifted_image_is_tracked_to_a_fraction_of_a_pixel() -> None:
    img = cv2.GaussianBlur(textured_image(np.random.default_rng(1)), (3, 3), 0)
    M = np.float32([[1, 0, 4.5], [0, 1, -3.0]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)
    c = detect_corners(img, 200)
    c = c[(c[:, 0] > 20) & (c[:, 0] < 300) & (c[:, 1] > 20) & (c[:, 1] < 220)]
    found, nxt = track_points(img, moved, c, TrackerOptions())
    assert found.mean() > 0.9
    np.testing.assert_allclose(np.median(nxt[found] - c[found], axis=0), [4.5, -3.0], atol=0.1)
    ok, back = track_checked(img, moved, c, TrackerOptions())
    assert ok.sum() >= 0.8 * found.sum()
    off, _ = track_points(img, moved, np.array([[-50.0, -50.0]], np.float32), TrackerOptions())
    assert not off.any()  # outside the image: not found


def test_relative_pose_of_a_rendered_stream(dense_stream: list) -> None:
    """Half the motions or more within 1° of rotation, each with a positive definite covariance (small steps
    next to turns have wrong basins that explain the tracks as well: the stream checks visual odometry against
    map points and fixes)."""
    tracker = FrameTracker()
    rot, good = [], 0
    for k, im in enumerate(dense_stream[:20]):
        out = tracker.track(read_gray(im.path), im.camera, 0.1 * k)
        if k == 0:
            assert out.relative is None
            continue
        assert out.tracks > 100
        if not out.relative.success:
            continue
        assert out.covariance is not None and out.covariance.shape == (5, 5)
        assert np.all(np.linalg.eigvalsh(out.covariance) > 0)
        truth = im.cam_from_world @ dense_stream[k - 1].cam_from_world.inverse()
        err = pose_errors(out.relative.pose, truth)[1]
        rot.append(err)
        good += err < 1.0
    assert len(rot) >= 12 and good >= 0.5 * len(rot) and np.median(rot) < 1.5


def test_the_tracker_refuses_motion_it_lost() -> None:
    """Two unrelated images: too few tracks agree (inlier ratio), no relative pose."""
    cam = Camera("PINHOLE", 320, 240, (250.0, 250.0, 160.0, 120.0))
    tracker = FrameTracker()
    tracker.track(textured_image(np.random.default_rng(2)), cam, 0.0)
    out = tracker.track(textured_image(np.random.default_rng(3)), cam, 0.1)
    assert out.relative is not None and not out.relative.success and out.covariance is None
    # another image size: nothing to track from
    out = tracker.track(
        textured_image(np.random.default_rng(4), 200, 300),
        Camera("PINHOLE", 300, 200, (250.0, 250.0, 150.0, 100.0)),
        0.2,
    )
    assert out.relative is None


def test_pose_from_points_with_outliers() -> None:
    rng = np.random.default_rng(5)
    truth = Pose.from_center(Rotation.from_rotvec([0.02, 0.3, -0.01]).as_matrix(), [1.0, -0.2, 3.0])
    X = truth.inverse().transform(rng.uniform([-4, -2, 4], [4, 2, 20], (120, 3)))  # in front of the camera
    x = truth.transform(X)
    rays = x[:, :2] / x[:, 2:]
    rays[:30] += rng.normal(0, 0.05, (30, 2))  # 25 % outliers
    prior = Pose(Rotation.from_rotvec([0.0, 0.28, 0.0]).as_matrix(), truth.t + [0.2, 0.0, -0.3])
    fit = pose_from_points(prior, X, rays, 500.0)
    assert fit is not None and fit[1] >= 85
    t_err, r_err = pose_errors(fit[0], truth)
    assert t_err < 1e-4 and r_err < 1e-3
    assert pose_from_points(prior, X[:10], rays[:10], 500.0) is None  # too few points
    assert pose_from_points(prior, X, rng.normal(0, 0.3, rays.shape), 500.0) is None  # nothing agrees


def test_world_points_tracked_through_frames(dense_stream: list) -> None:
    """Points of the first frame (depth from the renderer) tracked through 2 frames: the PnP
    pose of the last frame is near its truth."""
    first = dense_stream[0]
    corners = detect_corners(read_gray(first.path), 480)
    rays = first.camera.bearings_from_img(corners.astype(float))
    # depth from the truth: intersect with the scene is unknown here; use the points at the
    # depths a stereo pair would give: the renderer's depth image
    depth = cv2.imread(str(first.depth_path), cv2.IMREAD_UNCHANGED).astype(float) / first.depth_scale
    z = depth[np.rint(corners[:, 1]).astype(int), np.rint(corners[:, 0]).astype(int)]
    ok = z > 0
    X = first.cam_from_world.inverse().transform(rays[ok] * z[ok, None])
    history = FrameHistory(3)
    for k in range(3):
        history.append(0.1 * k, read_gray(dense_stream[k].path))
    points = track_through(history.since(0.0), TrackedPoints(0.0, corners[ok], X), TrackerOptions())
    assert points.stamp == pytest.approx(0.2) and points.hops == 2 and len(points) >= 20
    last = dense_stream[2]
    fit = pose_from_points(
        dense_stream[1].cam_from_world,
        points.points,
        last.camera.cam_from_img(points.pixels.astype(float)),
        last.camera.focal[0],
    )
    assert fit is not None
    t_err, r_err = pose_errors(fit[0], last.cam_from_world)
    assert t_err < 0.1 and r_err < 2.0
    assert history.since(5.0) == [] and len(history.since(0.1)) == 2
    history.append(0.3, read_gray(dense_stream[3].path))
    assert history.since(0.0) == []  # only the last 3 frames are kept


def test_direction_basis_is_orthonormal_and_options_are_checked() -> None:
    for u in ([0, 0, 1.0], [1.0, 2.0, -0.5], [0, 1e-9, 1]):
        B = direction_basis(np.asarray(u))
        n = np.asarray(u) / np.linalg.norm(u)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(B.T @ n, 0, atol=1e-12)
    with pytest.raises(InputError, match="threshold_px"):
        TrackerOptions(threshold_px=0)
    with pytest.raises(InputError, match="min_inlier_ratio"):
        TrackerOptions(min_inlier_ratio=1.5)
    with pytest.raises(InputError, match="corners"):
        TrackerOptions(corners=True)


def _project(pose: Pose, X: np.ndarray) -> np.ndarray:
    Xc = pose.transform(X)
    return Xc[:, :2] / Xc[:, 2:]


def test_points_pose_covariance_is_the_inverse_information_of_the_reprojections() -> None:
    rng = np.random.default_rng(3)
    pose = Pose.from_center(so3_exp(np.array([[0.02, 0.3, -0.01]]))[0], [1.0, 0.5, -2.0])
    X = pose.inverse().transform(np.column_stack([rng.uniform(-3, 3, (40, 2)), rng.uniform(4, 12, 40)]))
    x = _project(pose, X)
    sigma = 1.0 / 500.0
    cov = points_pose_covariance(pose, X, x, sigma)
    # the same by finite differences of the model (ω: R' = exp(ω) R; δc: c' = c + δc)
    J = np.zeros((2 * len(X), 6))
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        moved = Pose.from_center(so3_exp(d[None, :3])[0] @ pose.R, pose.center + d[3:])
        J[:, k] = ((_project(moved, X) - x) / h).ravel()
    expected = np.linalg.inv(J.T @ J) * sigma**2
    assert np.allclose(cov, expected, rtol=1e-4, atol=1e-12)
    # noisier rays (residuals above sigma) widen it by their RMS
    noisy = x + rng.normal(0, 5 * sigma, x.shape)
    assert np.trace(points_pose_covariance(pose, X, noisy, sigma)) > 10 * np.trace(cov)


def test_far_bunched_points_are_weak_along_the_view() -> None:
    rng = np.random.default_rng(4)
    pose = Pose.identity()
    near = np.column_stack([rng.uniform(-4, 4, (30, 2)), rng.uniform(3, 8, 30)])
    far = np.column_stack([rng.uniform(-1, 1, (30, 2)), rng.uniform(60, 70, 30)])
    std = [np.sqrt(points_pose_covariance(pose, X, _project(pose, X), 1e-3)[5, 5]) for X in (near, far)]
    assert std[1] > 20 * std[0]
    assert points_pose_covariance(pose, near[:3], _project(pose, near[:3]), 1e-3) is None


def test_blank_frames_are_told_from_dark_textured_ones() -> None:
    assert is_blank(np.zeros((120, 160), np.uint8))
    assert is_blank(np.full((120, 160), 255, np.uint8))
    dark = (np.random.default_rng(0).random((120, 160)) * 12).astype(np.uint8)  # underexposed, not blank
    assert not is_blank(dark)


def test_a_view_break_is_lost_corners_or_tracks_that_fit_no_motion_but_not_standing_still() -> None:
    failed = RelativePoseEstimate(None, False, "too_few_inliers", num_inliers=5)
    moved = Tracked(failed, tracks=200, flow_px=40.0)
    assert view_broken(moved, 20, None)  # nothing says it was a fast turn
    assert view_broken(moved, 20, 3.0)  # odometry: a small turn
    assert not view_broken(moved, 20, 25.0)  # odometry: a turn too fast to track
    assert not view_broken(Tracked(failed, tracks=200, flow_px=0.5), 20, None)  # standing still
    lost = Tracked(RelativePoseEstimate(None, False, "too_few_matches"), tracks=3, flow_px=60.0)
    assert view_broken(lost, 20, None)
    ok = Tracked(
        RelativePoseEstimate(Pose.identity(), True, "success", num_inliers=150), tracks=200, flow_px=9.0
    )
    assert not view_broken(ok, 20, None) and not view_broken(Tracked(None), 20, None)
