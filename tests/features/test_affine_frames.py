"""Affine frames of matches from SIFT orientation and scale: the OpenCV angle convention on a
synthetically warped image, the accuracy of the similarity frame, and the normalization."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from textured_images import textured_image

from planarloc.features.affine_frames import (
    affine_residual,
    normalized_affine,
    similarity_affine,
    similarity_affine_from_keypoints,
)
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError


def rot(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def sift_matches_under_warp(L: np.ndarray, seed: int = 0, size: tuple[int, int] = (480, 640)):
    """SIFT on a textured image and on its warp ``uv' = L (uv - c) + c'``; matches kept when the
    descriptor match agrees with the true warp within 1.5 px. Returns the keypoints and matches."""
    h, w = size
    img = textured_image(np.random.default_rng(seed), h, w)
    c = np.array([w / 2, h / 2])
    W = np.hstack([L, (c - L @ c)[:, None]])
    warped = cv2.warpAffine(img, W, (w, h), flags=cv2.INTER_LINEAR, borderValue=128)
    sift = cv2.SIFT_create(nfeatures=1500)
    k1, d1 = sift.detectAndCompute(img, None)
    k2, d2 = sift.detectAndCompute(warped, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = []
    for m, n in pairs:
        if m.distance < 0.8 * n.distance:
            p1 = np.array(k1[m.queryIdx].pt)
            p2 = np.array(k2[m.trainIdx].pt)
            if np.linalg.norm(W[:, :2] @ p1 + W[:, 2] - p2) < 1.5:
                good.append(m)
    return k1, k2, good


@pytest.mark.parametrize("angle_deg, scale", [(30.0, 1.0), (-70.0, 1.3), (120.0, 0.8)])
def test_sift_similarity_frame_approximates_the_true_affine(angle_deg: float, scale: float) -> None:
    """Rotation + zoom of the image content: the SIFT frame recovers the map (OpenCV angle
    convention: a rotation by α in pixel coordinates adds α to KeyPoint.angle)."""
    L = scale * rot(np.deg2rad(angle_deg))
    k1, k2, good = sift_matches_under_warp(L)
    assert len(good) >= 50
    A = similarity_affine_from_keypoints(k1, k2, good)
    rel, angle, log_scale = affine_residual(A, np.broadcast_to(L, A.shape))
    assert abs(np.median(angle)) < 1.0
    assert np.median(np.abs(angle)) < 4.0
    assert abs(np.median(log_scale)) < 0.05
    assert np.median(np.abs(log_scale)) < 0.12
    assert np.median(rel) < 0.15


def test_similarity_frame_misses_the_tilt_of_a_slanted_patch() -> None:
    """A horizontal stretch (the 'transition tilt' of planar motion) is outside the similarity
    model: the frame's error is bounded by the tilt, and shown by the residual."""
    tilt = 1.4
    L = np.diag([1.0 / tilt, 1.0])
    k1, k2, good = sift_matches_under_warp(L, seed=1)
    assert len(good) >= 30
    A = similarity_affine_from_keypoints(k1, k2, good)
    rel, _angle, log_scale = affine_residual(A, np.broadcast_to(L, A.shape))
    # scale is about sqrt(det) = 1/sqrt(tilt); the anisotropy itself cannot be represented
    assert abs(np.median(log_scale) - np.log(1 / np.sqrt(tilt))) < 0.15
    best_similarity_rel = np.linalg.norm(L - np.eye(2) / np.sqrt(tilt)) / np.linalg.norm(L)
    assert np.median(rel) >= 0.5 * best_similarity_rel
    assert np.median(rel) < best_similarity_rel + 0.25


def test_similarity_affine_formula_and_dmatch_and_index_inputs() -> None:
    A = similarity_affine([10.0, 350.0], [4.0, 2.0], [40.0, 20.0], [8.0, 2.0])
    np.testing.assert_allclose(A[0], 2.0 * rot(np.deg2rad(30.0)), atol=1e-12)
    np.testing.assert_allclose(A[1], rot(np.deg2rad(-330.0)), atol=1e-12)
    kq = [cv2.KeyPoint(5.0, 5.0, 4.0, 10.0), cv2.KeyPoint(1.0, 1.0, 2.0, 350.0)]
    kr = [cv2.KeyPoint(5.0, 5.0, 2.0, 20.0), cv2.KeyPoint(7.0, 7.0, 8.0, 40.0)]
    np.testing.assert_allclose(similarity_affine_from_keypoints(kq, kr, [(0, 1), (1, 0)]), A, atol=1e-12)
    dm = [cv2.DMatch(0, 1, 0.0), cv2.DMatch(1, 0, 0.0)]
    np.testing.assert_allclose(similarity_affine_from_keypoints(kq, kr, dm), A, atol=1e-12)
    with pytest.raises(InputError):
        similarity_affine([0.0], [0.0], [0.0], [1.0])
    with pytest.raises(InputError):
        similarity_affine([0.0, 1.0], [1.0], [0.0], [1.0])


def test_normalized_affine_pinhole_is_the_focal_scaling() -> None:
    cq = Camera("PINHOLE", 640, 480, (500.0, 520.0, 320.0, 240.0))
    cr = Camera("PINHOLE", 800, 600, (700.0, 690.0, 400.0, 300.0))
    A = np.array([[[1.1, 0.2], [-0.1, 0.9]]])
    out = normalized_affine(A, [[100.0, 50.0]], [[300.0, 200.0]], cq, cr)
    expect = np.diag([1 / 700.0, 1 / 690.0]) @ A[0] @ np.diag([500.0, 520.0])
    np.testing.assert_allclose(out[0], expect, rtol=1e-9)


def test_normalized_affine_with_distortion_matches_a_warp_through_the_cameras() -> None:
    """Pixels of a small patch mapped through: undistort (query) -> true normalized affine ->
    distort (reference). The normalized map recovered from the pixel Jacobian equals the truth."""
    cq = Camera("OPENCV", 640, 480, (500.0, 500.0, 320.0, 240.0, -0.2, 0.05, 0.001, -0.002))
    cr = Camera("OPENCV", 640, 480, (480.0, 470.0, 330.0, 250.0, 0.1, -0.02, 0.0, 0.001))
    A_true = np.array([[0.9, 0.15], [-0.05, 1.1]])
    uq = np.array([[500.0, 100.0]])
    xq = cq.cam_from_img(uq)[0]
    xr = np.array([0.1, -0.2])

    def pix_map(u: np.ndarray) -> np.ndarray:
        return cr.img_from_cam(xr + (cq.cam_from_img(u) - xq) @ A_true.T)

    h = 1e-3
    A_px = np.stack(
        [
            (pix_map(uq + [h, 0]) - pix_map(uq - [h, 0]))[0] / (2 * h),
            (pix_map(uq + [0, h]) - pix_map(uq - [0, h]))[0] / (2 * h),
        ],
        axis=1,
    )
    ur = cr.img_from_cam(xr[None])
    out = normalized_affine(A_px[None], uq, ur, cq, cr, step_px=1e-2)
    np.testing.assert_allclose(out[0], A_true, atol=1e-5)
