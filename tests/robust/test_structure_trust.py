"""Promises of the structure-aware estimator (issue 17): 2D-3D constraints are seen by the
uncertainty, map pose errors do not outvote them, flat or distant scenes are refused."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.estimators import SIGMA_FLOOR_PX
from planarloc.robust.final_refinement import refine_until_stable
from planarloc.robust.options import RansacOptions
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.planar_scene import homography_inlier_ratio
from planarloc.robust.problem import build_problem
from planarloc.robust.refinement import RefineSettings
from planarloc.synthetic.scenes import make_scene

FACADE_CAMERA = Camera("PINHOLE", 768, 512, (690.0, 690.0, 384.0, 256.0))


def road_with_map_errors(seed: int, rotation_error_deg: float = 0.3, share_3d: float = 0.3) -> tuple:
    """A straight road (query collinear with 5 map images, KITTI-like) whose map poses are off by
    ``rotation_error_deg`` / 2 cm, with 2D-3D points (2 cm error) for ``share_3d`` of the matches, as
    the local structure of the retrieved map images gives them."""
    rng = np.random.default_rng(seed)
    sc = make_scene(
        rng,
        num_refs=5,
        matches_per_pair=400,
        noise_px=1.0,
        outlier_ratio=0.2,
        collinear=True,
        with_depth=True,
        track_pool=3.0,
    )
    pairs = []
    for p in sc.pairs:
        R = (
            Rotation.from_rotvec(rng.normal(0, math.radians(rotation_error_deg), 3)).as_matrix()
            @ p.ref_pose.R
        )
        c = p.ref_pose.center + rng.normal(0, 0.02, 3)
        X = p.ref_points3d.copy()
        X[rng.random(len(X)) > share_3d] = np.nan
        has = ~np.isnan(X[:, 0])
        X[has] += rng.normal(0, 0.02, (int(has.sum()), 3))
        pairs.append(replace(p, ref_pose=Pose(R, -R @ c), ref_points3d=X))
    return sc, pairs


@pytest.mark.parametrize("seed", range(6))
def test_hundreds_of_2d3d_inliers_are_never_degenerate_scale(seed: int) -> None:
    """Map pose errors bend the 2D-2D cost along the road; the 2D-3D constraints fix the position.
    Before issue 17 a 6DoF 2D-2D pose kilometres of cost-equivalent valley away was a "rival" and
    seed 0 came back degenerate_scale with 172 2D-3D inliers."""
    sc, pairs = road_with_map_errors(seed)
    est = estimate_absolute_pose(sc.query_camera, pairs, "auto", RansacOptions(seed=seed))
    assert est.success, f"{est.status}: {est.message}"
    assert est.num_inliers_3d >= 200
    err = pose_errors(est.pose, sc.query_pose)[0]
    assert err < 0.05 and err <= 3 * est.position_std_m + 0.05


KITTI_CAMERA = Camera("PINHOLE", 1241, 376, (718.9, 718.9, 607.2, 185.2))


def forward_road(
    seed: int, map_rotation_error_deg: float, matches_per_pair: int = 300
) -> tuple[Pose, list[PairMatches]]:
    """A straight road seen by a forward-looking KITTI camera: map images every 4 m along it, the
    query 0.5-1.5 m past the first one (KITTI kitti_seq1 frame 000001 against the every-4th map),
    house fronts 4-12 m to either side up to 60 m ahead. Query keypoints are matched in ~1.25 map
    images on average, so a few hundred become tracks, triangulated by the estimator along the
    viewing direction (small angles, depth uncertain). The map poses handed to the estimator are
    off by ``map_rotation_error_deg`` per axis and 2 cm; pixels 0.5 px, 20 % wrong matches."""
    rng = np.random.default_rng(seed)
    n = 6000
    X = np.c_[
        rng.choice([-1.0, 1.0], n) * rng.uniform(4, 12, n), rng.uniform(-4, 1.6, n), rng.uniform(2, 60, n)
    ]

    def on_road(z: float) -> Pose:
        R = rotation_from_yaw(rng.uniform(-0.02, 0.02))
        return Pose(R, -R @ np.array([0.0, 0.0, z]))

    def seen(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        Xc = X @ pose.R.T + pose.t
        front = Xc[:, 2] > 1.0
        uv = KITTI_CAMERA.img_from_cam(np.where(front[:, None], Xc, 1.0))
        return uv, front & (uv >= 0).all(axis=1) & (uv < (KITTI_CAMERA.width, KITTI_CAMERA.height)).all(
            axis=1
        )

    query = on_road(rng.uniform(0.5, 1.5))
    uv_q, vis_q = seen(query)
    pool = rng.choice(np.flatnonzero(vis_q), min(int(vis_q.sum()), 4 * matches_per_pair), replace=False)
    pairs = []
    for k in range(5):
        ref = on_road(4.0 * k)
        uv_r, vis_r = seen(ref)
        common = pool[vis_r[pool]]
        ids = rng.choice(common, min(matches_per_pair, len(common)), replace=False)
        q = uv_q[ids] + rng.normal(0, 0.5, (len(ids), 2))
        r = uv_r[ids] + rng.normal(0, 0.5, (len(ids), 2))
        wrong = rng.random(len(ids)) < 0.2
        r[wrong] = rng.uniform((0, 0), (KITTI_CAMERA.width, KITTI_CAMERA.height), (int(wrong.sum()), 2))
        R = Rotation.from_rotvec(rng.normal(0, math.radians(map_rotation_error_deg), 3)).as_matrix() @ ref.R
        pairs.append(
            PairMatches(
                Pose.from_center(R, ref.center + rng.normal(0, 0.02, 3)),
                KITTI_CAMERA,
                q,
                r,
                query_indices=ids,
            )
        )
    return query, pairs


def test_points_triangulated_along_the_road_carry_their_map_images_pose_errors() -> None:
    """Issue 17, promises: >= 99 % of successes within 3σ + 5 cm, here where the map's pose errors
    (as large as the options say, 0.3°) reach the position through the points. Every track of one
    map image shares that image's error, so it does not average out over hundreds of tracks like
    pixel noise. Before the points' dependence on their map images' poses was propagated, 3 of 31
    successes broke their promise (4.2, 7.9 and 6.3 σ off) and the mean (error / σ)² was 4.5."""
    ratios = []
    for seed in range(40):
        truth, pairs = forward_road(seed, map_rotation_error_deg=0.3)
        est = estimate_absolute_pose(
            KITTI_CAMERA, pairs, "auto", RansacOptions(seed=seed, map_rotation_std_deg=0.3)
        )
        if est.success:
            err = pose_errors(est.pose, truth)[0]
            assert err <= 3 * est.position_std_m + 0.05, (seed, err, est.position_std_m)
            ratios.append(err / est.position_std_m)
        else:
            assert est.status in ("ambiguous_pose", "degenerate_scale"), est.status
    assert len(ratios) >= 25
    # Honest, not needlessly pessimistic (the worst-axis std of an elongated covariance is about
    # 1.5x the median error; a std twice too large would put the median ratio near 0.3).
    assert 0.3 < np.median(ratios) and np.mean(np.square(ratios)) < 1.0


def with_ghost_matches(
    truth: Pose, pairs: list[PairMatches], seed: int, ghosts: int = 300, behind_m: float = 100.0
) -> list[PairMatches]:
    """``pairs`` plus ``ghosts`` wrong 2D-2D matches per map image that a pose ``behind_m`` back
    along the road explains exactly (repeated structure along a road does this to real matches:
    forward motion's epipolar lines all run through the image centre). They are query keypoints
    of their own, so they give no 2D-3D constraint."""
    rng = np.random.default_rng(1000 + seed)
    far = Pose.from_center(truth.R, truth.center - np.array([0.0, 0.0, behind_m]))
    size = np.array([KITTI_CAMERA.width, KITTI_CAMERA.height])
    out, next_id = [], 100_000
    for p in pairs:
        q, r = [], []
        while len(q) < ghosts:
            X = np.array(
                [rng.choice([-1.0, 1.0]) * rng.uniform(4, 12), rng.uniform(-4, 1.6), rng.uniform(2, 60)]
            )
            Xc = [pose.R @ X + pose.t for pose in (far, p.ref_pose)]
            if min(x[2] for x in Xc) < 1.0:
                continue
            uv = [KITTI_CAMERA.img_from_cam(x[None])[0] for x in Xc]
            if all((u >= 0).all() and (u < size).all() for u in uv):
                q.append(uv[0] + rng.normal(0, 0.5, 2))
                r.append(uv[1] + rng.normal(0, 0.5, 2))
        out.append(
            replace(
                p,
                query_points=np.vstack([p.query_points, q]),
                ref_points=np.vstack([p.ref_points, r]),
                query_indices=np.concatenate([p.query_indices, np.arange(next_id, next_id + ghosts)]),
            )
        )
        next_id += ghosts
    return out


@pytest.mark.parametrize("seed", range(4))
def test_a_pose_the_points_fix_is_not_given_up_for_a_far_2d2d_pose(seed: int) -> None:
    """Along a road 2D-2D constraints barely see the position: a pose far back along it can
    explain more 2D-2D matches (here 300 wrong ones per map image) than the truth and win the
    searches on cost, with none of the 2D-3D constraints; its position is unobservable. The pose
    the points fix is then judged instead (a search on the points alone finds it), and kept when
    it passes. Before, seeds 0, 1 and 2 came back degenerate_scale (poses 113-142 m off, 0 2D-3D
    inliers; kitti_seq1 frame 000002 on a compact map, 146 m off)."""
    truth, pairs = forward_road(seed, map_rotation_error_deg=0.0)
    est = estimate_absolute_pose(
        KITTI_CAMERA, with_ghost_matches(truth, pairs, seed), "auto", RansacOptions(seed=seed)
    )
    assert est.success, f"{est.status}: {est.message}"
    assert est.num_inliers_3d >= 200
    err = pose_errors(est.pose, truth)[0]
    assert err < 0.1 and err <= 3 * est.position_std_m + 0.05, (err, est.position_std_m)


def test_map_prior_keeps_2d2d_from_outvoting_the_points() -> None:
    """On the collinear road with map errors and few 2D-3D points (5 % of ~1,600 matches), the final
    refinement with the map prior lands closer to the truth than the one that trusts the map poses."""
    errors = {True: [], False: []}
    for seed in range(6):
        sc, pairs = road_with_map_errors(seed, rotation_error_deg=0.3, share_3d=0.05)
        pb = build_problem(sc.query_camera, pairs).with_reprojection_threshold(0.5)
        T = sc.query_pose
        for prior in (True, False):
            R, t, *_ = refine_until_stable(
                T.R,
                T.t,
                pb.arrays,
                RefineSettings(
                    4.0, 2.0, 6, SIGMA_FLOOR_PX, math.radians(0.3) if prior else 0.0, 0.02 if prior else 0.0
                ),
                4,
            )
            errors[prior].append(pose_errors(Pose(R, t), T)[0])
    assert np.median(errors[True]) < 0.6 * np.median(errors[False]), errors
    assert max(errors[True]) < 0.05


def test_map_prior_refinement_is_exact_on_a_perfect_map() -> None:
    sc = make_scene(np.random.default_rng(4), num_refs=4, matches_per_pair=80, noise_px=0.0, with_depth=True)
    pb = build_problem(sc.query_camera, sc.pairs)
    T = sc.query_pose
    start = Pose.from_center(
        Rotation.from_rotvec([0.004, -0.003, 0.002]).as_matrix() @ T.R,
        T.center + np.array([0.05, -0.02, 0.04]),
    )
    R, t, H, sigma, *_ = refine_until_stable(
        start.R,
        start.t,
        pb.arrays,
        RefineSettings(4.0, 2.0, 10, SIGMA_FLOOR_PX, math.radians(0.1), 0.02),
        4,
    )
    dc, dr = pose_errors(Pose(R, t), T)
    assert dc < 1e-6 and dr < 1e-5
    assert np.all(np.linalg.eigvalsh(H) > 0)


# ---- a distant flat facade --------------------------------------------------------------------------
def facade(seed: int, matches: int = 30, depth: float = 20.0) -> tuple[Pose, list[PairMatches]]:
    """Four map images within 2 m of each other see a facade ``depth`` metres away (±0.3 m of
    relief); the query stands 5-10 m in front of it; ``matches`` per map image, 1 px noise."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-8, 8, 3000), rng.uniform(-6, 1, 3000), depth + rng.uniform(-0.3, 0.3, 3000)]

    def at(c: np.ndarray, yaw: float) -> Pose:
        R = rotation_from_yaw(yaw)
        return Pose(R, -R @ c)

    def project(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        Xc = X @ pose.R.T + pose.t
        uv = Xc[:, :2] / Xc[:, 2:] * 690.0 + [384.0, 256.0]
        return uv, (Xc[:, 2] > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < 768) & (uv[:, 1] >= 0) & (uv[:, 1] < 512)

    refs = [
        at(np.array([rng.uniform(-2, 2), 0.0, rng.uniform(-2, 2)]), rng.uniform(-0.1, 0.1)) for _ in range(4)
    ]
    query = at(np.array([rng.uniform(-3, 3), 0.0, depth - rng.uniform(10, 15)]), rng.uniform(-0.2, 0.2))
    uq, seen = project(query)
    pool = rng.choice(np.flatnonzero(seen), int(2.5 * matches), replace=False)
    pairs = []
    for ref in refs:
        ur, ok = project(ref)
        ids = rng.choice(pool[ok[pool]], matches, replace=False)
        pairs.append(
            PairMatches(
                ref,
                FACADE_CAMERA,
                uq[ids] + rng.normal(0, 1.0, (matches, 2)),
                ur[ids] + rng.normal(0, 1.0, (matches, 2)),
                query_indices=ids,
            )
        )
    return query, pairs


def test_a_distant_flat_facade_with_few_inliers_is_a_failure() -> None:
    """2D-2D matches of a flat facade 30 m away, seen by map images within 2 m of each other:
    rotation and translation are entangled. Before issue 17 these were successes 0.6 m / 2.5°
    off with a position std of 0.13-0.15 m (at 20 m, 14 of 30 queries; two broke the promise)."""
    statuses = []
    for seed in range(20):
        query, pairs = facade(seed, depth=30.0)
        est = estimate_absolute_pose(FACADE_CAMERA, pairs, "auto", RansacOptions(structure="none", seed=seed))
        assert not est.success, (seed, pose_errors(est.pose, query), est.position_std_m)
        statuses.append(est.status)
    assert statuses.count("degenerate_structure") >= 15, statuses


@pytest.mark.parametrize("structure", ["none", "tracks"])
def test_facade_successes_keep_their_promise(structure: str) -> None:
    """At 20 m a few queries are localized (tracks: points triangulated between the map images);
    every success lies within 3 std + 5 cm. Tracks: 3 of 30 since the points carry their map
    images' pose errors (7 before): the options' 0.1° of map rotation moves a point triangulated
    over a 2 m baseline at 20 m by ~0.35 m, so four of the seven had a std beyond 0.3 m."""
    successes = 0
    for seed in range(30):
        query, pairs = facade(seed)
        est = estimate_absolute_pose(
            FACADE_CAMERA, pairs, "auto", RansacOptions(structure=structure, seed=seed)
        )
        if est.success:
            successes += 1
            err = pose_errors(est.pose, query)[0]
            assert err <= 3 * est.position_std_m + 0.05, (seed, err, est.position_std_m)
    assert successes >= (1 if structure == "none" else 3)


def test_homography_inlier_ratio_tells_a_plane_from_depth() -> None:
    rng = np.random.default_rng(5)
    a, b = Pose(np.eye(3), np.zeros(3)), Pose(rotation_from_yaw(0.1), np.array([1.0, 0.0, 0.3]))
    for relief, planar in ((0.0, True), (8.0, False)):
        X = np.c_[rng.uniform(-5, 5, 200), rng.uniform(-3, 3, 200), 12.0 + rng.uniform(0, relief, 200)]
        xa = X @ a.R.T + a.t
        xb = X @ b.R.T + b.t
        xa, xb = xa / xa[:, 2:], xb / xb[:, 2:]
        xa[:, :2] += rng.normal(0, 0.5 / 500, (200, 2))
        ratio = homography_inlier_ratio(xa, xb, np.arange(200), np.array([500.0, 500.0]), 4.0)
        assert (ratio > 0.95) if planar else (ratio < 0.8), (relief, ratio)


# ---- input validation ------------------------------------------------------------------------------
def test_point_covariances_are_validated() -> None:
    sc = make_scene(np.random.default_rng(6), num_refs=2, matches_per_pair=20, with_depth=True)
    p = sc.pairs[0]
    with pytest.raises(InputError, match="without ref_points3d"):
        PairMatches(
            p.ref_pose, p.ref_camera, p.query_points, p.ref_points, ref_points3d_cov=np.zeros((20, 3, 3))
        )
    with pytest.raises(InputError, match="ref_points3d_cov"):
        replace(p, ref_points3d_cov=np.zeros((19, 3, 3)))
    with pytest.raises(InputError, match="symmetric positive semi-definite"):
        replace(
            p,
            ref_points3d_cov=np.tile(
                np.array([[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), (20, 1, 1)
            ),
        )
    nan = np.full((20, 3, 3), np.nan)
    with pytest.raises(InputError, match="finite where"):
        replace(p, ref_points3d_cov=nan)
    partner, jac = np.ones(20), np.zeros((20, 2, 3, 6))
    with pytest.raises(InputError, match="both or neither"):
        replace(p, ref_points3d_partner=partner)
    with pytest.raises(InputError, match="whole numbers >= -1"):
        replace(p, ref_points3d_partner=np.full(20, -2), ref_points3d_pose_jac=jac)
    with pytest.raises(InputError, match="ref_points3d_pose_jac"):
        replace(p, ref_points3d_partner=partner, ref_points3d_pose_jac=np.zeros((20, 3, 6)))
    with pytest.raises(InputError, match="finite where a point has a partner"):
        replace(p, ref_points3d_partner=partner, ref_points3d_pose_jac=np.full((20, 2, 3, 6), np.nan))
    replace(p, ref_points3d_partner=np.full(20, -1), ref_points3d_pose_jac=np.full((20, 2, 3, 6), np.nan))
    with pytest.raises(InputError, match="without ref_points3d"):
        PairMatches(
            p.ref_pose,
            p.ref_camera,
            p.query_points,
            p.ref_points,
            ref_points3d_partner=partner,
            ref_points3d_pose_jac=jac,
        )


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_threshold_3d_is_validated(value: float) -> None:
    with pytest.raises(InputError, match="threshold_3d_px"):
        RansacOptions(threshold_3d_px=value)


def test_a_success_reports_a_calibrated_6x6_covariance_in_ros_order() -> None:
    """Centre (x, y, z), then the rotation vector of world_from_camera about the world axes: the
    squared Mahalanobis errors of 60 generated queries average about 6 (6 degrees of freedom)."""
    mahalanobis = []
    for seed in range(60):
        sc = make_scene(np.random.default_rng(seed), num_refs=4, matches_per_pair=60, noise_px=1.0)
        est = estimate_absolute_pose(
            sc.query_camera,
            sc.pairs,
            "auto",
            RansacOptions(structure="none", map_rotation_std_deg=0.0, map_position_std_m=0.0, seed=seed),
        )
        if not est.success:
            continue
        C = est.covariance
        assert C.shape == (6, 6) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
        assert np.linalg.eigvalsh(C[:3, :3])[-1] == pytest.approx(est.position_std_m**2, rel=1e-6)
        phi = Rotation.from_matrix(est.pose.R.T @ sc.query_pose.R).as_rotvec()
        e = np.r_[est.pose.center - sc.query_pose.center, phi]
        mahalanobis.append(e @ np.linalg.solve(C, e))
        assert "covariance_xyz_rotvec" in est.to_dict()
    assert len(mahalanobis) >= 50
    assert 2.0 < np.mean(mahalanobis) < 12.0
