"""Local affine frames of matches from SIFT keypoint orientation and scale.

A SIFT keypoint carries a similarity frame: a position, a scale (OpenCV ``KeyPoint.size``, the
diameter of the described region, in pixels) and an orientation (``KeyPoint.angle``, in degrees
in [0, 360)). In OpenCV the angle is that of the dominant gradient direction **in pixel
coordinates (x right, y down)**: the direction ``(cos a, sin a)`` in ``(u, v)``. OpenCV's
``calcOrientationHist`` measures ``atan2(-∂I/∂v, ∂I/∂u)`` (y up) and stores ``360 - angle``.
A rotation of the image content by ``α`` in pixel coordinates (``[[cos α, -sin α], [sin α, cos α]]``
applied to ``(u, v)``, clockwise on screen for α > 0) therefore adds ``α`` to the keypoint angle,
and a zoom by ``s`` multiplies the size by ``s``.

The local affine map of a match ``(query keypoint 1, reference keypoint 2)``, pixels to pixels::

    A_px = ∂uv_ref / ∂uv_query ≈ (s2 / s1) · R(a2 - a1)                       (similarity)

This is the frame used by Barath & Hajder's and Guan et al.'s affine-correspondence solvers when
only rotation-and-scale covariant features are available (Guan et al., CVPR 2020, Sec. 5.2 use
affine-covariant detectors instead). :func:`normalized_affine` turns it into the map between
**normalized** image coordinates that :func:`planarloc.solvers.relpose_planar_1ac.relpose_planar_1ac`
takes, through the cameras' Jacobians (exact for distortion too).

Accuracy (tests/features/test_affine_frames.py, ``benchmarks/solvers_1ac.py``):

- SIFT's orientation is quantised in 36 bins and parabola-interpolated; on a textured image the
  per-keypoint angle error is typically a few degrees, the log-scale error ~5–15 %. Both errors
  of the two keypoints add up in the match.
- A similarity has 4 DoF of an affinity's 6 (see :func:`affine_residual`): it cannot express the
  shear and anisotropic stretch (the "transition tilt" of our paper, Sec. III-B) that a ground
  robot sees on slanted surfaces. Where the true local affine has a tilt ``τ`` the similarity
  frame is off by ``O(τ - 1)`` in those entries; it is exact only for fronto-parallel patches
  under rotation about the optical axis and zoom. The 1AC solver uses all four entries, so on
  real matches it yields a hypothesis to be verified and refined, not a final pose.
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError, check_array

#: Pixel step of the central differences of :func:`normalized_affine` (exact for pinholes).
JACOBIAN_STEP_PX = 0.5


def similarity_affine(
    angle_query_deg: object, size_query: object, angle_ref_deg: object, size_ref: object
) -> np.ndarray:
    """Local affine maps of N matches from their keypoints' orientation and scale.

    Args:
        angle_query_deg: (N,) OpenCV ``KeyPoint.angle`` of the query keypoints, degrees
            (pixel coordinates, x right, y down; module docstring).
        size_query: (N,) OpenCV ``KeyPoint.size`` of the query keypoints, pixels (> 0).
        angle_ref_deg, size_ref: (N,) the same for the matching reference keypoints.

    Returns:
        (N, 2, 2) ``A_px = (s_ref / s_query) R(a_ref - a_query)``, with ``d uv_ref ≈ A_px d uv_query``.

    Raises:
        InputError: different lengths, non-finite values or non-positive sizes.
    """
    aq = check_array("angle_query_deg", angle_query_deg, (None,))
    sq = check_array("size_query", size_query, (None,))
    ar = check_array("angle_ref_deg", angle_ref_deg, (None,))
    sr = check_array("size_ref", size_ref, (None,))
    if not len(aq) == len(sq) == len(ar) == len(sr):
        raise InputError(f"keypoint arrays: different lengths ({len(aq)}, {len(sq)}, {len(ar)}, {len(sr)})")
    if np.any(sq <= 0) or np.any(sr <= 0):
        raise InputError("keypoint sizes: expected > 0 (OpenCV KeyPoint.size), got a non-positive size")
    alpha = np.deg2rad(ar - aq)
    s = sr / sq
    c, si = s * np.cos(alpha), s * np.sin(alpha)
    return np.stack([np.stack([c, -si], -1), np.stack([si, c], -1)], -2)


def similarity_affine_from_keypoints(kps_query, kps_ref, matches) -> np.ndarray:
    """:func:`similarity_affine` of OpenCV matches.

    Args:
        kps_query, kps_ref: sequences of ``cv2.KeyPoint``.
        matches: (N, 2) int indices ``(query, ref)`` or a sequence of ``cv2.DMatch``
            (``queryIdx`` into ``kps_query``, ``trainIdx`` into ``kps_ref``).

    Returns:
        (N, 2, 2) pixel affine maps ``∂uv_ref / ∂uv_query``.
    """
    if len(matches) and hasattr(matches[0], "queryIdx"):
        idx = np.array([(m.queryIdx, m.trainIdx) for m in matches], dtype=np.int64).reshape(-1, 2)
    else:
        idx = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    aq = np.array([kps_query[i].angle for i in idx[:, 0]], dtype=np.float64)
    sq = np.array([kps_query[i].size for i in idx[:, 0]], dtype=np.float64)
    ar = np.array([kps_ref[i].angle for i in idx[:, 1]], dtype=np.float64)
    sr = np.array([kps_ref[i].size for i in idx[:, 1]], dtype=np.float64)
    return similarity_affine(aq, sq, ar, sr)


def _normalized_jacobian(camera: Camera, uv: np.ndarray, h: float) -> np.ndarray:
    """(N, 2, 2) ``∂(x/z, y/z) / ∂(u, v)`` of ``camera.cam_from_img`` by central differences."""
    n = len(uv)
    pts = np.concatenate([uv + [h, 0.0], uv - [h, 0.0], uv + [0.0, h], uv - [0.0, h]])
    xy = camera.cam_from_img(pts).reshape(4, n, 2)
    J = np.empty((n, 2, 2))
    J[:, :, 0] = (xy[0] - xy[1]) / (2 * h)
    J[:, :, 1] = (xy[2] - xy[3]) / (2 * h)
    return J


def normalized_affine(
    affine_px: object,
    uv_query: object,
    uv_ref: object,
    cam_query: Camera,
    cam_ref: Camera,
    step_px: float = JACOBIAN_STEP_PX,
) -> np.ndarray:
    """Pixel affine maps of N matches as maps between normalized image coordinates.

    ``A_norm = J_ref(uv_ref) · A_px · J_query(uv_query)⁻¹`` with ``J = ∂(x/z, y/z)/∂(u, v)`` of
    the cameras' undistortion (:meth:`Camera.cam_from_img`), by central differences of
    ``step_px`` pixels; for pinholes this is ``diag(1/fx_r, 1/fy_r) A_px diag(fx_q, fy_q)``.

    Args:
        affine_px: (N, 2, 2) ``∂uv_ref / ∂uv_query`` in pixels (e.g. :func:`similarity_affine`).
        uv_query, uv_ref: (N, 2) matched pixel coordinates (OpenCV convention).
        cam_query, cam_ref: the two cameras.

    Returns:
        (N, 2, 2) ``∂(x_r, y_r) / ∂(x_q, y_q)``, NaN for a match outside a camera's model.
    """
    A = check_array("affine_px", affine_px, (None, 2, 2))
    uq = check_array("uv_query", uv_query, (len(A), 2))
    ur = check_array("uv_ref", uv_ref, (len(A), 2))
    if not step_px > 0:
        raise InputError(f"step_px: expected > 0, got {step_px!r}")
    Jq = _normalized_jacobian(cam_query, uq, step_px)
    Jr = _normalized_jacobian(cam_ref, ur, step_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        det = Jq[:, 0, 0] * Jq[:, 1, 1] - Jq[:, 0, 1] * Jq[:, 1, 0]
        Jq_inv = np.stack(
            [np.stack([Jq[:, 1, 1], -Jq[:, 0, 1]], -1), np.stack([-Jq[:, 1, 0], Jq[:, 0, 0]], -1)], -2
        )
        Jq_inv /= det[:, None, None]
    return Jr @ A @ Jq_inv


def affine_residual(estimate: object, truth: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far (N, 2, 2) affine maps are from the true ones: ``(rel, angle_deg, log_scale)``.

    ``rel = ‖estimate - truth‖_F / ‖truth‖_F``; ``angle_deg`` and ``log_scale`` compare the
    rotation ``atan2(a10 - a01, a00 + a11)`` and the scale ``sqrt(|det|)`` of the two maps (the
    similarity part; the remaining shear and stretch only show in ``rel``).
    """
    E = check_array("estimate", estimate, (None, 2, 2))
    T = check_array("truth", truth, (len(E), 2, 2))
    rel = np.linalg.norm(E - T, axis=(1, 2)) / np.linalg.norm(T, axis=(1, 2))

    def rot(M: np.ndarray) -> np.ndarray:
        return np.arctan2(M[:, 1, 0] - M[:, 0, 1], M[:, 0, 0] + M[:, 1, 1])

    d = rot(E) - rot(T)
    angle = np.rad2deg(np.arctan2(np.sin(d), np.cos(d)))
    log_scale = 0.5 * (np.log(np.abs(np.linalg.det(E))) - np.log(np.abs(np.linalg.det(T))))
    return rel, angle, log_scale
