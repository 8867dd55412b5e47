"""Local structure: 3D points of map keypoints, triangulated between the retrieved map images.

The map is only posed images, so at query time the map images retrieved for a query are
matched with each other and their correspondences are triangulated with the images' known
poses (no reconstruction is stored, no bundle adjustment: adding an image to a map stays an
insert). A query keypoint matched to a map keypoint that has such a point becomes a 2D-3D
constraint, which fixes the position along a road or corridor where 2D-2D constraints cannot
(NOTES.md: triangulate-then-PnP localizes KITTI to a centimetre). Not in the paper.

Only the map keypoints the query matched are triangulated, against every other retrieved image:
a directed match ``a → b`` is computed for a keypoint of ``a`` once and kept in an LRU cache
(:class:`PairMatchCache`), so consecutive queries of a stream, which retrieve the same map
images, reuse it. Matching is the query matcher's (RootSIFT, FGINN ratio test); a candidate
must then satisfy the epipolar geometry of the two known poses, triangulate in front of both
cameras with a reprojection error within the inlier threshold in both, and at a triangulation
angle of at least ``min_angle_deg``. Each point carries its covariance from the keypoint noise
(first order, ``KEYPOINT_STD_PX``) and its motion under corrections of the two map images'
poses, which the estimator propagates into the query's position uncertainty: a far point
triangulated at a small angle is uncertain in depth, and a query seen from elsewhere inherits
that; a map pose error moves every point of its image together (it does not average out).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planarloc.features.extract import Features
from planarloc.features.matching import DEFAULT_RATIO, match_features
from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import triangulate_points, triangulation_uncertainty
from planarloc.geometry.pose import Pose
from planarloc.robust.structure import KEYPOINT_STD_PX

logger = logging.getLogger(__name__)

DEFAULT_MIN_ANGLE_DEG = 1.0
"""Smallest triangulation angle kept; the covariance accounts for the depth error above it."""

CONSISTENCY_WINDOW = 2.0
"""Matches between two map images whose reprojection error under the images' known poses is within
this many times the inlier threshold measure how well the poses agree with the images."""
CONSISTENT_RESIDUAL_PX = 0.5
"""Median of that error where the poses agree (keypoint noise alone): 0.3-0.6 px between KITTI
``kitti_seq1`` frames 16-40."""
RESIDUAL_PER_ROTATION = 0.5
"""Median reprojection error, in focal lengths, per radian of rotation error of one of the two
poses (a rotation moves a point by ``f·δ``; the triangulation absorbs part of it, the median
of a spread of directions is smaller)."""

_UNKNOWN, _NONE = -2, -1


@dataclass(frozen=True, eq=False)
class MapView:
    """What local structure needs of one retrieved map image.

    Attributes:
        name: the map image's name (the cache key).
        features: its local features.
        cam_from_world: its pose.
        camera: its intrinsics.
    """

    name: str
    features: Features
    cam_from_world: Pose
    camera: Camera


@dataclass(frozen=True)
class ViewPoints:
    """3D points of some keypoints of one map view.

    Attributes:
        X: (N, 3) world points, NaN rows where the keypoint has none.
        cov: (N, 3, 3) their covariance (m²), NaN rows where there is no point.
        angle_deg: (N,) triangulation angle (0 where there is no point).
        partner: (N,) index (into the views) of the view it was triangulated with, -1 if none.
        pose_jac: (N, 2, 3, 6) motion of each point when the pose of this view (``[:, 0]``) or
            of its partner (``[:, 1]``) is corrected
            (:func:`~planarloc.geometry.epipolar.triangulation_uncertainty`), NaN rows where
            there is no point: the map's pose errors, shared by every point of a view.
        pose_residual_px: median reprojection error, under the known poses, of this view's
            matches with the other views (within :data:`CONSISTENCY_WINDOW` times the
            threshold); NaN if none: how well this view's pose agrees with its neighbours'.
    """

    X: np.ndarray
    cov: np.ndarray
    angle_deg: np.ndarray
    partner: np.ndarray
    pose_jac: np.ndarray
    pose_residual_px: float = float("nan")


def map_rotation_std_deg(residual_px: float, focal_px: float) -> float:
    """Rotation error per map image (degrees) that a median reprojection error ``residual_px`` of
    matches between map images under their known poses implies, beyond keypoint noise
    (:data:`CONSISTENT_RESIDUAL_PX`); 0 where the poses agree with the images or nothing was measured.

    ``kitti_seq1`` frames 0-12 (the sequence's first seconds): the KITTI poses disagree with the
    images by 2.0-2.5 px between frames 0, 4, 8 and 16 (a relative rotation of 0.3-0.8° against
    the pairs' own essential matrices) against 0.3-0.6 px from frame 16 on; points triangulated
    from them put a query 1.2-1.5 m off along the road with a position std of 0.2-0.26 m when the
    map was assumed good to ``map_rotation_std_deg`` = 0.1°.
    """
    if not (np.isfinite(residual_px) and residual_px > CONSISTENT_RESIDUAL_PX and focal_px > 0):
        return 0.0
    excess = np.sqrt(residual_px**2 - CONSISTENT_RESIDUAL_PX**2)
    return float(np.degrees(excess / (RESIDUAL_PER_ROTATION * focal_px)) / np.sqrt(2.0))


@dataclass
class _Directed:
    """Matches of keypoints of view a in view b, computed on demand."""

    match: np.ndarray  # (|a|,) int64: _UNKNOWN, _NONE, or the matched keypoint of b
    X: np.ndarray  # (|a|, 3) world point where match >= 0
    angle: np.ndarray  # (|a|,) degrees
    residual: np.ndarray  # (|a|,) px: reprojection error under the known poses, NaN unless measured


class PairMatchCache:
    """LRU cache of directed map-image matches and their triangulated points.

    Keyed by the two images' names and the matching settings; ``max_pairs`` directed pairs
    (48 bytes per keypoint of a: about 190 KB each for 4,000 keypoints) are kept.
    """

    def __init__(self, max_pairs: int = 512) -> None:
        self.max_pairs = int(max_pairs)
        self._entries: OrderedDict[tuple, _Directed] = OrderedDict()
        self.hits = 0
        self.computed = 0

    def directed(self, a: MapView, b: MapView, rows: np.ndarray, settings: tuple) -> _Directed:
        """The entry of ``a → b`` with every keypoint of ``rows`` computed."""
        key = (a.name, b.name, settings)
        entry = self._entries.get(key)
        if entry is None:
            n = len(a.features)
            entry = _Directed(
                np.full(n, _UNKNOWN, dtype=np.int64), np.full((n, 3), np.nan), np.zeros(n), np.full(n, np.nan)
            )
            self._entries[key] = entry
            if len(self._entries) > self.max_pairs:
                self._entries.popitem(last=False)
        else:
            self._entries.move_to_end(key)
        todo = rows[entry.match[rows] == _UNKNOWN]
        self.hits += len(rows) - len(todo)
        if len(todo):
            self.computed += len(todo)
            _match_and_triangulate(a, b, todo, entry, *settings)
        return entry


def _normalized(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    return camera.bearings_from_img(np.asarray(pixels, dtype=float))


def _match_and_triangulate(
    a: MapView,
    b: MapView,
    rows: np.ndarray,
    entry: _Directed,
    ratio: float,
    max_error_px: float,
    min_angle_deg: float,
) -> None:
    """Fill ``entry`` for keypoints ``rows`` of a: match into b, keep those consistent with the
    two known poses (epipolar, in front, reprojection within ``max_error_px``, angle)."""
    fa = a.features
    sub = Features(fa.keypoints[rows], fa.descriptors[rows], fa.scales[rows])
    m = match_features(sub, b.features, ratio=ratio, mutual=False)
    entry.match[rows] = _NONE
    if len(m) == 0:
        return
    ia, ib = rows[m[:, 0]], m[:, 1]
    xa = _normalized(a.camera, fa.keypoints[ia])
    xb = _normalized(b.camera, b.features.keypoints[ib])
    ok = np.isfinite(xa).all(axis=1) & np.isfinite(xb).all(axis=1)
    Ra, ta = a.cam_from_world.R, a.cam_from_world.t
    Rb, tb = b.cam_from_world.R, b.cam_from_world.t
    X, angle = triangulate_points(
        (Ra, ta), (Rb, tb), np.where(ok[:, None], xa, 1.0), np.where(ok[:, None], xb, 1.0)
    )
    err = np.zeros(len(X))
    for R, t, x, cam in ((Ra, ta, xa, a.camera), (Rb, tb, xb, b.camera)):
        Xc = X @ R.T + t
        (fx, fy) = cam.focal
        with np.errstate(invalid="ignore", divide="ignore"):
            du = (Xc[:, 0] / Xc[:, 2] - x[:, 0] / x[:, 2]) * fx
            dv = (Xc[:, 1] / Xc[:, 2] - x[:, 1] / x[:, 2]) * fy
            err = np.maximum(err, np.hypot(du, dv))
            ok &= Xc[:, 2] > 0
    ok &= np.isfinite(X).all(axis=1)
    measured = ok & (err <= CONSISTENCY_WINDOW * max_error_px)  # every angle: far points see rotations best
    entry.residual[ia[measured]] = err[measured]
    ok &= (err <= max_error_px) & (angle >= min_angle_deg)
    ia, ib = ia[ok], ib[ok]
    entry.match[ia] = ib
    entry.X[ia] = X[ok]
    entry.angle[ia] = angle[ok]


def view_points(
    views: Sequence[MapView],
    keypoints: Sequence[np.ndarray],
    cache: PairMatchCache,
    *,
    ratio: float = DEFAULT_RATIO,
    max_error_px: float = 2.0,
    min_angle_deg: float = DEFAULT_MIN_ANGLE_DEG,
    keypoint_std_px: float = KEYPOINT_STD_PX,
) -> list[ViewPoints]:
    """3D points of the given keypoints of each view, triangulated with the other views.

    Args:
        views: the retrieved map images (at least two for any point).
        keypoints: per view, (N_k,) keypoint indices to give points (e.g. those the query matched).
        cache: directed match cache, shared across queries.
        ratio: ratio-test threshold of the matcher.
        max_error_px: reprojection tolerance in both views, pixels.
        min_angle_deg: smallest triangulation angle.
        keypoint_std_px: the map images' keypoint noise, for the points' covariance (the map's
            measurement, :attr:`planarloc.map.pose_accuracy.MapPoseAccuracy.keypoint_std_px`).

    Returns:
        one :class:`ViewPoints` per view, rows in the order of ``keypoints[k]``; each keypoint
        takes the partner view that triangulates it at the widest angle.
    """
    settings = (float(ratio), float(max_error_px), float(min_angle_deg))
    out = []
    for k, (view, rows) in enumerate(zip(views, keypoints)):
        rows = np.asarray(rows, dtype=np.int64)
        n = len(rows)
        X = np.full((n, 3), np.nan)
        angle = np.zeros(n)
        partner = np.full(n, -1, dtype=np.int64)
        residuals = []
        for j, other in enumerate(views):
            if j == k or other.name == view.name or n == 0:
                continue
            entry = cache.directed(view, other, rows, settings)
            residuals.append(entry.residual[rows])
            better = (entry.match[rows] >= 0) & (entry.angle[rows] > angle)
            X[better] = entry.X[rows[better]]
            angle[better] = entry.angle[rows[better]]
            partner[better] = j
        cov = np.full((n, 3, 3), np.nan)
        jac = np.full((n, 2, 3, 6), np.nan)
        has = partner >= 0
        if has.any():
            others = [views[int(j)] for j in partner[has]]
            cov[has], jac[has] = triangulation_uncertainty(
                X[has],
                (view.cam_from_world.R, view.cam_from_world.t),
                (
                    np.array([o.cam_from_world.R for o in others]),
                    np.array([o.cam_from_world.t for o in others]),
                ),
                view.camera.focal,
                np.array([o.camera.focal for o in others], dtype=float),
                keypoint_std_px,
            )
        bad = ~(np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(jac).all(axis=(1, 2, 3)))
        X[bad], angle[bad], partner[bad], cov[bad], jac[bad] = np.nan, 0.0, -1, np.nan, np.nan
        pooled = np.concatenate(residuals) if residuals else np.zeros(0)
        pooled = pooled[np.isfinite(pooled)]
        out.append(
            ViewPoints(X, cov, angle, partner, jac, float(np.median(pooled)) if len(pooled) else float("nan"))
        )
    return out
