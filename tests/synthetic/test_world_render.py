"""Renderer: determinism, depth against an independent ray cast, SIFT richness and geometry, timing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from planarloc.synthetic.world import Plane, Room, World, build_sessions, get_preset, render_frame, shrunk
from planarloc.synthetic.world.render import NEAR, clip_polygon_near, render


@pytest.fixture(scope="module")
def tiny():
    return build_sessions(shrunk(get_preset("office")), seed=0)


@pytest.fixture(scope="module")
def office():
    return build_sessions(get_preset("office"), seed=0)


def raycast_depth(
    world: World, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
) -> np.ndarray:
    """(H, W) z-depth of the nearest plane hit by each pixel-centre ray (0 = none), brute force, float64."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # z = 1: ray parameter = depth
    rays = rays_cam @ R  # world directions (R^T applied to row vectors)
    center = -R.T @ t
    best = np.full((height, width), np.inf)
    for plane in world.planes:
        n = np.cross(plane.edge_u, plane.edge_v)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to the plane
            lam = ((plane.origin - center) @ n) / denom
            hit = center + lam[..., None] * rays - plane.origin
            a = hit @ plane.edge_u / (plane.edge_u @ plane.edge_u)
            b = hit @ plane.edge_v / (plane.edge_v @ plane.edge_v)
            ok = (lam >= NEAR) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (lam < best)
            best[ok] = lam[ok]
    best[~np.isfinite(best)] = 0.0
    return best


def test_same_seed_same_bytes_and_other_seed_differs(tiny):
    m2, q2 = build_sessions(shrunk(get_preset("office")), seed=0)
    m, q = tiny
    for a, b in ((m, m2), (q, q2)):
        for i in (0, len(a) - 1):
            img_a, dep_a = render_frame(a, i)
            img_b, dep_b = render_frame(b, i)
            assert img_a.tobytes() == img_b.tobytes()
            assert dep_a.tobytes() == dep_b.tobytes()
    other_m, _ = build_sessions(shrunk(get_preset("office")), seed=1)
    assert render_frame(m, 0)[0].tobytes() != render_frame(other_m, 0)[0].tobytes()


def test_render_output_types(tiny):
    m, _ = tiny
    image, depth = render(m.world, m.K, m.R[0], m.t[0], m.width, m.height)
    assert image.shape == (m.height, m.width, 3) and image.dtype == np.uint8
    assert depth.shape == (m.height, m.width) and depth.dtype == np.float32
    assert np.all(depth > 0), "inside a closed room every pixel sees a surface"
    assert depth.max() < np.hypot(m.world.room.size_x, m.world.room.size_z) + 1


@pytest.mark.parametrize("session_index", [0, 1])
def test_depth_matches_raycast(tiny, session_index):
    session = tiny[session_index]  # map (upright) and query (tilted by up to 1 degree)
    for i in range(0, len(session), 2):
        _, depth = render(session.world, session.K, session.R[i], session.t[i], session.width, session.height)
        expected = raycast_depth(
            session.world, session.K, session.R[i], session.t[i], session.width, session.height
        )
        assert np.all(expected > 0)
        rel = np.abs(depth.astype(np.float64) - expected) / expected
        # Pixels whose ray grazes a silhouette edge may legitimately pick the other surface.
        assert np.mean(rel < 1e-3) > 0.998, f"frame {i}: {np.mean(rel >= 1e-3):.4%} pixels off"
        assert np.median(rel) < 1e-5


def test_backprojected_depth_reprojects_into_another_view(tiny):
    m, q = tiny
    K, Kinv = m.K, np.linalg.inv(m.K)
    _, depth_m = render(m.world, K, m.R[0], m.t[0], m.width, m.height)
    Rq, tq = q.R[0], q.t[0]
    _, depth_q = render(q.world, K, Rq, tq, q.width, q.height)
    u, v = np.meshgrid(np.arange(m.width), np.arange(m.height))
    pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(np.float64)
    pts_cam = (pix @ Kinv.T) * depth_m.reshape(-1, 1)
    pts_world = (pts_cam - m.t[0]) @ m.R[0]
    in_q = pts_world @ Rq.T + tq
    z = in_q[:, 2]
    proj = in_q @ K.T
    uq, vq = proj[:, 0] / z, proj[:, 1] / z
    ui, vi = np.rint(uq).astype(int), np.rint(vq).astype(int)
    inside = (z > NEAR) & (ui >= 0) & (ui < q.width) & (vi >= 0) & (vi < q.height)
    near_centre = (
        inside & (np.abs(uq - ui) < 0.05) & (np.abs(vq - vi) < 0.05)
    )  # transfer lands on a pixel centre
    assert near_centre.sum() > 20
    seen = depth_q[vi[near_centre], ui[near_centre]].astype(np.float64)
    rel = np.abs(seen - z[near_centre]) / z[near_centre]
    visible = rel < 1e-3  # the rest is occluded in the query view (seen depth smaller)
    assert visible.mean() > 0.5
    assert np.all(seen[~visible] < z[near_centre][~visible] * (1 + 1e-3) + 0.02)


def test_plane_behind_and_edge_on_cameras_render_nothing():
    tex = np.full((8, 8, 3), 200, np.uint8)
    world = World(
        (Plane(np.array([-1.0, -1.0, -2.0]), np.array([2.0, 0, 0]), np.array([0, 2.0, 0]), tex),),
        Room(4, 4, 2.5),
    )
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    image, depth = render(world, K, np.eye(3), np.zeros(3), 64, 48)  # plane at z = -2: behind
    assert not image.any() and not depth.any()
    image, depth = render(world, K, np.eye(3), np.array([0.0, 0.0, 4.0]), 64, 48)  # now at z = +2
    assert np.allclose(depth[depth > 0], 2.0, rtol=1e-6) and (depth > 0).mean() > 0.5
    edge_on = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # camera looking along the plane
    image, depth = render(world, K, edge_on, np.zeros(3), 64, 48)
    assert (depth > 0).mean() < 0.05


def test_near_clipping_polygon():
    square = np.array([[-1.0, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]])
    clipped = clip_polygon_near(square, 0.05)
    assert len(clipped) == 4 and np.all(clipped[:, 2] >= 0.05 - 1e-12)
    assert len(clip_polygon_near(square - [0, 0, 5], 0.05)) == 0


def test_bad_camera_raises(tiny):
    m, _ = tiny
    with pytest.raises(ValueError, match="rotation"):
        render(m.world, m.K, 2 * np.eye(3), m.t[0], 16, 16)
    with pytest.raises(ValueError, match="K must"):
        render(m.world, np.eye(2), m.R[0], m.t[0], 16, 16)
    with pytest.raises(ValueError, match="image size"):
        render(m.world, m.K, m.R[0], m.t[0], 0, 16)


def _sift(image: np.ndarray):
    return cv2.SIFT_create().detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)


def test_office_frames_have_many_sift_features_and_geometrically_correct_matches(office):
    m, q = office
    for i in range(0, len(m), 10):
        kps, _ = _sift(render_frame(m, i)[0])
        assert len(kps) > 300, f"map frame {i}: only {len(kps)} SIFT keypoints"

    # The query frame nearest (in position) to map frame 0, and correspondences through GT depth.
    c_m = -np.einsum("nji,nj->ni", m.R, m.t)
    c_q = -np.einsum("nji,nj->ni", q.R, q.t)
    j = int(np.argmin(np.linalg.norm(c_q - c_m[0], axis=1)))
    img_m, depth_m = render_frame(m, 0)
    img_q, _ = render_frame(q, j)
    kp_m, des_m = _sift(img_m)
    kp_q, des_q = _sift(img_q)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(des_m, des_q, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    assert len(good) > 50
    x_m = np.array([kp_m[g.queryIdx].pt for g in good])
    x_q = np.array([kp_q[g.trainIdx].pt for g in good])

    # Ground-truth transfer of map keypoints into the query view through the rendered depth.
    ui, vi = np.rint(x_m).astype(int).T
    z = depth_m[vi, ui].astype(np.float64)
    pts = (np.column_stack([x_m, np.ones(len(x_m))]) @ np.linalg.inv(m.K).T) * z[:, None]
    R_qm = q.R[j] @ m.R[0].T
    t_qm = q.t[j] - R_qm @ m.t[0]
    proj = (pts @ R_qm.T + t_qm) @ q.K.T
    transfer_err = np.linalg.norm(proj[:, :2] / proj[:, 2:] - x_q, axis=1)
    correct = transfer_err < 3.0
    assert correct.sum() > 40 and correct.mean() > 0.5, (
        f"{correct.sum()} of {len(good)} matches agree with the ground truth"
    )

    # The ground-truth epipolar geometry holds for those matches, and RANSAC recovers it.
    E_gt = np.array([[0, -t_qm[2], t_qm[1]], [t_qm[2], 0, -t_qm[0]], [-t_qm[1], t_qm[0], 0]]) @ R_qm
    Kinv = np.linalg.inv(m.K)
    F_gt = Kinv.T @ E_gt @ Kinv
    h_m = np.column_stack([x_m, np.ones(len(x_m))])
    h_q = np.column_stack([x_q, np.ones(len(x_q))])
    Fx, Ftx = h_m @ F_gt.T, h_q @ F_gt
    sampson = np.einsum("ij,ij->i", h_q, Fx) ** 2 / (
        Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    )
    assert np.median(np.sqrt(sampson[correct])) < 1.0
    E, inliers = cv2.findEssentialMat(x_m, x_q, m.K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    _, R_est, t_est, _ = cv2.recoverPose(E[:3], x_m, x_q, m.K, mask=inliers)
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_qm) - 1) / 2, -1, 1)))
    assert angle < 2.0, f"relative rotation off by {angle:.2f} degrees"
    cos_t = float(t_est.ravel() @ t_qm / np.linalg.norm(t_qm))
    assert cos_t > 0.9, f"translation direction off (cos {cos_t:.3f})"
