"""Local structure: map keypoints triangulated between retrieved map images with known poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import projection_jacobians, triangulation_uncertainty
from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.localize.local_structure import (
    CONSISTENT_RESIDUAL_PX,
    MapView,
    PairMatchCache,
    map_rotation_std_deg,
    view_points,
)

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def pose_at(x: float, z: float, yaw: float) -> Pose:
    R = rotation_from_yaw(yaw)
    return Pose(R, -R @ np.array([x, 0.0, z]))


def views_of(
    points: np.ndarray,
    poses: list[Pose],
    rng: np.random.Generator,
    noise_px: float = 0.0,
    distractors: int = 50,
) -> tuple[list[MapView], list[np.ndarray]]:
    """One MapView per pose: the visible points' projections with a descriptor per point (the
    same in every view), plus distractor keypoints; and per view the keypoint index of each point
    (-1 where not visible)."""
    desc = rng.normal(size=(len(points), 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    views, index = [], []
    for k, pose in enumerate(poses):
        Xc = points @ pose.R.T + pose.t
        uv = CAMERA.img_from_cam(np.where(Xc[:, 2:] > 0, Xc, 1.0))
        vis = (Xc[:, 2] > 0.5) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
        ids = np.flatnonzero(vis)
        kp = uv[ids] + rng.normal(0.0, noise_px, (len(ids), 2))
        extra = rng.normal(size=(distractors, 128)).astype(np.float32)
        extra /= np.linalg.norm(extra, axis=1, keepdims=True)
        kp = np.vstack([kp, rng.uniform([0, 0], [640, 480], (distractors, 2))]).astype(np.float32)
        d = np.vstack([desc[ids], extra])
        views.append(MapView(f"map{k}", Features(kp, d, np.ones(len(kp), np.float32)), pose, CAMERA))
        where = np.full(len(points), -1)
        where[ids] = np.arange(len(ids))
        index.append(where)
    return views, index


def scene(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    return np.c_[rng.uniform(-6, 6, n), rng.uniform(-2, 2, n), rng.uniform(6, 20, n)]


def test_points_are_exact_on_noise_free_views_and_come_from_the_widest_partner() -> None:
    rng = np.random.default_rng(0)
    X = scene(rng)
    views, index = views_of(X, [pose_at(0, 0, 0), pose_at(0.5, 1.5, 0.05), pose_at(-0.4, 3.0, -0.05)], rng)
    rows = [np.flatnonzero(np.isin(np.arange(len(v.features)), ix[ix >= 0])) for v, ix in zip(views, index)]
    out = view_points(views, rows, PairMatchCache())
    for k, (pts, ix) in enumerate(zip(out, index)):
        point_of = {int(kp): i for i, kp in enumerate(ix) if kp >= 0}
        has = np.flatnonzero(np.isfinite(pts.X[:, 0]))
        assert len(has) > 0.5 * len(rows[k])  # most points seen twice get a point
        truth = X[[point_of[int(r)] for r in rows[k][has]]]
        np.testing.assert_allclose(pts.X[has], truth, atol=1e-4)  # float32 keypoints
        assert np.all(pts.partner[has] != k) and np.all(pts.angle_deg[has] >= 1.0)
        assert np.isfinite(pts.cov[has]).all() and np.all(np.linalg.eigvalsh(pts.cov[has]) > 0)
        # Moving both map images' centres by d moves each point by d.
        np.testing.assert_allclose(
            pts.pose_jac[has, 0, :, 3:] + pts.pose_jac[has, 1, :, 3:],
            np.broadcast_to(np.eye(3), (len(has), 3, 3)),
            atol=1e-6,
        )
        assert np.isnan(pts.pose_jac[~np.isfinite(pts.X[:, 0])]).all()
        # The partner is the view that sees the point at the widest triangulation angle.
        centres = [v.cam_from_world.center for v in views]
        for i, Xi in zip(has, truth):
            angles = {
                j: np.degrees(
                    np.arccos(
                        np.clip(
                            (Xi - centres[k])
                            @ (Xi - centres[j])
                            / np.linalg.norm(Xi - centres[k])
                            / np.linalg.norm(Xi - centres[j]),
                            -1,
                            1,
                        )
                    )
                )
                for j in range(len(views))
                if j != k and index[j][point_of[int(rows[k][i])]] >= 0
            }
            assert pts.partner[i] == max(angles, key=angles.get)
            assert pts.angle_deg[i] == pytest.approx(angles[pts.partner[i]], abs=1e-3)


def test_wrong_matches_are_refused_by_the_known_poses() -> None:
    """A descriptor match that breaks the two views' epipolar geometry gives no point."""
    rng = np.random.default_rng(1)
    X = scene(rng)
    views, index = views_of(X, [pose_at(0, 0, 0), pose_at(0.6, 2.0, 0.0)], rng, distractors=0)
    # Swap the descriptors of pairs of points in the second view: a perfect descriptor match
    # to the wrong place.
    d = views[1].features.descriptors.copy()
    both = np.flatnonzero((index[0] >= 0) & (index[1] >= 0))
    a, b = both[:40:2], both[1:40:2]
    d[index[1][a]], d[index[1][b]] = (
        views[1].features.descriptors[index[1][b]],
        views[1].features.descriptors[index[1][a]],
    )
    views[1] = MapView(
        views[1].name,
        Features(views[1].features.keypoints, d, views[1].features.scales),
        views[1].cam_from_world,
        CAMERA,
    )
    swapped = index[0][np.r_[a, b]]
    out = view_points(views, [swapped, np.zeros(0, dtype=np.int64)], PairMatchCache())
    assert not np.isfinite(out[0].X[:, 0]).any()


def test_the_cache_computes_each_keypoint_once() -> None:
    rng = np.random.default_rng(2)
    X = scene(rng)
    views, index = views_of(X, [pose_at(0, 0, 0), pose_at(0.5, 1.5, 0.0), pose_at(0.0, 3.0, 0.0)], rng)
    cache = PairMatchCache()
    rows = [np.arange(0, len(v.features), 2) for v in views]
    first = view_points(views, rows, cache)
    computed = cache.computed
    again = view_points(views, rows, cache)
    assert cache.computed == computed and cache.hits >= sum(len(r) for r in rows) * (len(views) - 1)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.X, b.X)
    view_points(views, [np.arange(1, len(v.features), 2) for v in views], cache)  # new keypoints only
    assert cache.computed > computed


def test_triangulation_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    X = np.array([[1.0, 0.5, 15.0], [-2.0, -0.5, 8.0]])
    a, b = pose_at(0, 0, 0), pose_at(1.0, 1.0, 0.05)
    sigma = 1.0
    predicted = triangulation_uncertainty(X, (a.R, a.t), (b.R, b.t), CAMERA.focal, CAMERA.focal, sigma).cov
    Ja, Jb = (projection_jacobians(X, p.R, p.t, CAMERA.focal) for p in (a, b))  # σ² (Σ_v J_vᵀ J_v)⁻¹
    np.testing.assert_allclose(
        predicted,
        sigma**2 * np.linalg.inv(Ja.transpose(0, 2, 1) @ Ja + Jb.transpose(0, 2, 1) @ Jb),
        rtol=1e-9,
    )
    assert np.array_equal(predicted, predicted.transpose(0, 2, 1))
    from planarloc.geometry.epipolar import triangulate_points

    samples = []
    for _ in range(4000):
        xs = []
        for pose in (a, b):
            uv = CAMERA.img_from_cam(X @ pose.R.T + pose.t) + rng.normal(0.0, sigma, (len(X), 2))
            xs.append(CAMERA.bearings_from_img(uv))
        samples.append(triangulate_points((a.R, a.t), (b.R, b.t), *xs)[0])
    samples = np.array(samples)
    for i in range(len(X)):
        empirical = np.cov(samples[:, i].T)
        # the dominant (depth) variance within 15 %, the directions agree
        lp, le = np.linalg.eigvalsh(predicted[i])[-1], np.linalg.eigvalsh(empirical)[-1]
        assert lp == pytest.approx(le, rel=0.15)
        vp, ve = np.linalg.eigh(predicted[i])[1][:, -1], np.linalg.eigh(empirical)[1][:, -1]
        assert abs(vp @ ve) > 0.99


def _least_squares_point(poses: list[Pose], pixels: list[np.ndarray], X0: np.ndarray) -> np.ndarray:
    """Gauss-Newton on the reprojection errors of one point in the given views."""
    X = X0.copy()
    for _ in range(30):
        r = np.concatenate(
            [CAMERA.img_from_cam((X @ p.R.T + p.t)[None])[0] - uv for p, uv in zip(poses, pixels)]
        )
        J = np.vstack([projection_jacobians(X[None], p.R, p.t, CAMERA.focal)[0] for p in poses])
        X = X - np.linalg.lstsq(J, r, rcond=None)[0]
    return X


def test_pose_jacobians_follow_the_least_squares_point_when_a_map_pose_is_corrected() -> None:
    """A map image's pose correction (ω, d) moves the point that best fits the fixed keypoints by
    ``∂X/∂(ω, d)``; forward motion (the baseline along the viewing direction) makes it large."""
    X = np.array([[2.0, 0.5, 20.0], [-3.0, 1.0, 15.0], [0.5, -0.2, 40.0]])
    a, b = pose_at(0, 0, 0), pose_at(0.3, 3.0, 0.05)
    pixels = [CAMERA.img_from_cam(X @ p.R.T + p.t) for p in (a, b)]
    S = triangulation_uncertainty(X, (a.R, a.t), (b.R, b.t), CAMERA.focal, CAMERA.focal, 1.0).pose_jac
    assert S.shape == (3, 2, 3, 6)
    eps = 1e-6
    for view in range(2):
        for k in range(6):
            step = np.zeros(6)
            step[k] = eps
            p = (a, b)[view]
            R = Rotation.from_rotvec(step[:3]).as_matrix() @ p.R
            moved = Pose.from_center(R, p.center + step[3:])
            poses = [moved, b] if view == 0 else [a, moved]
            numeric = np.array(
                [
                    (_least_squares_point(poses, [uv[i] for uv in pixels], X[i]) - X[i]) / eps
                    for i in range(len(X))
                ]
            )
            np.testing.assert_allclose(
                S[:, view, :, k], numeric, rtol=1e-3, atol=1e-3 * np.abs(numeric).max()
            )
    # 0.1° of yaw of one view moves a point 40 m ahead of a 3 m forward baseline by metres.
    assert np.abs(S[2, 1, :, 1]).max() * np.radians(0.1) > 0.5


@pytest.mark.parametrize("seed", [0, 1])
def test_a_map_pose_that_disagrees_with_its_image_is_measured(seed: int) -> None:
    """The median reprojection error of map-image matches under their known poses is keypoint
    noise where the poses agree with the images, and grows with a rotation error of one pose;
    map_rotation_std_deg turns it into that error's size (KITTI's first seconds: 2 px)."""
    rng = np.random.default_rng(seed)
    X = scene(rng, 600)
    poses = [pose_at(0, 0, 0), pose_at(0.3, 2.0, 0.02), pose_at(-0.3, 4.0, -0.02)]
    views, index = views_of(X, poses, rng, noise_px=0.3)
    rows = [ix[ix >= 0] for ix in index]
    agree = view_points(views, rows, PairMatchCache())
    assert all(p.pose_residual_px < CONSISTENT_RESIDUAL_PX for p in agree)
    assert all(map_rotation_std_deg(p.pose_residual_px, 500.0) == 0.0 for p in agree)
    error_deg = 0.5
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    R = Rotation.from_rotvec(np.radians(error_deg) * axis).as_matrix() @ poses[0].R
    stored = Pose(R, -R @ poses[0].center)  # the map says this; the image was taken at poses[0]
    views[0] = MapView(views[0].name, views[0].features, stored, CAMERA)
    off = view_points(views, rows, PairMatchCache())
    assert off[0].pose_residual_px > 3 * max(p.pose_residual_px for p in agree)
    measured = map_rotation_std_deg(off[0].pose_residual_px, 500.0)
    assert 0.5 * error_deg < measured < 2.0 * error_deg
    assert map_rotation_std_deg(float("nan"), 500.0) == 0.0
