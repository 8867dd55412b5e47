"""Does a map image see the query at all? Epipolar support of a pair's matches, against chance.

A failed estimate has many causes; one of them points at a different fix than the others: the
map does not hold the place (status ``not_in_map``, issue 32). Whether a map image *sees* the
query does not depend on the map's poses or on planar motion: two views of one scene have
matches that one essential matrix explains (``x_refᵀ E x_query = 0``, the paper's Eq. (1)
without the planar constraint), while matches between unrelated images are explained only by
chance. The support of a pair is the number of matches the best essential matrix explains within
``threshold_px`` (OpenCV's 5-point RANSAC, on undistorted normalized coordinates, so cameras of
different intrinsics compare). Random matches reach few: in 40 draws per size (uniform points,
640 × 480, 1 px), 99 % of the best essential matrices explained at most 6 of 8 matches, 9 of 30,
11 of 120 and 16 of 300 (the 5 of the minimal sample among them). A pair *sees* the query when
its support reaches :func:`seeing_support`: :data:`MIN_SEEN_INLIERS` plus
:data:`CHANCE_SHARE` of its matches — about twice what chance gives at every size.
"""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import check_array

#: the fewest matches one essential matrix must explain for a map image to see the query
MIN_SEEN_INLIERS = 15
#: the share of a pair's matches added to that floor (chance grows slowly with the matches)
CHANCE_SHARE = 0.05


def seeing_support(num_matches: int) -> int:
    """The epipolar support (matches one essential matrix explains) that ``num_matches`` matches
    need for their map image to see the query (module docstring)."""
    return int(np.ceil(MIN_SEEN_INLIERS + CHANCE_SHARE * max(int(num_matches), 0)))


def epipolar_support(
    query_points: np.ndarray,
    ref_points: np.ndarray,
    query_camera: Camera,
    ref_camera: Camera,
    threshold_px: float = 1.0,
    seed: int = 0,
) -> int:
    """The most matches one essential matrix explains (5-point RANSAC, 99.9 % confidence).

    Args:
        query_points, ref_points: (N, 2) matched pixels in the query and the map image.
        query_camera, ref_camera: their intrinsics (matches are undistorted and normalized).
        threshold_px: the epipolar distance that counts as explained, in pixels (converted with
            the mean focal length of the two cameras).
        seed: OpenCV's random generator seed (the same input gives the same count).

    Returns:
        The inlier count among the matches at distinct pixels on both sides (0 with fewer than 5
        such matches that can be undistorted, or when no essential matrix fits them).
    """
    q = check_array("query_points", query_points, (None, 2))
    r = check_array("ref_points", ref_points, (len(q), 2))
    xq, xr = query_camera.cam_from_img(q), ref_camera.cam_from_img(r)
    ok = np.isfinite(xq).all(axis=1) & np.isfinite(xr).all(axis=1)
    # One vote per place: a keypoint detected twice (SIFT's second orientation) or matched twice
    # counts once on each side, so repeated points cannot make an essential matrix look supported.
    ok &= _first_of_each(np.round(q)) & _first_of_each(np.round(r))
    if int(ok.sum()) < 5:
        return 0
    focal = float(np.mean([*query_camera.focal, *ref_camera.focal]))
    cv2.setRNGSeed(int(seed))
    try:
        E, mask = cv2.findEssentialMat(
            xq[ok], xr[ok], np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=float(threshold_px) / focal
        )
    except cv2.error:  # a degenerate set (e.g. repeated points) has no essential matrix at all
        return 0
    if E is None or mask is None:
        return 0
    return int(np.count_nonzero(mask))


def _first_of_each(rows: np.ndarray) -> np.ndarray:
    """(N,) True at the first occurrence of each distinct row of ``rows`` (N, 2)."""
    keep = np.zeros(len(rows), dtype=bool)
    keep[np.unique(rows, axis=0, return_index=True)[1]] = True
    return keep
