"""A query's matches with its retrieved map images, packaged for the estimator.

:class:`MapMatcher` keeps what outlives one query (the map images' features for a coarse pass,
their depth maps, the local-structure matches between map images: :mod:`.local_structure`) and
turns a query's features into :class:`~planarloc.robust.pair_matches.PairMatches`, one per map
image with enough matches (:meth:`MapMatcher.match`), with the 3D points of the map keypoints the
query matched (local structure, measured depth) and how much the map poses behind them disagree
with their images. The settings of one call come in :class:`MatchSettings` (the
:class:`~planarloc.localize.localizer.Localizer` builds them from its configuration).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from planarloc.features.extract import Features
from planarloc.features.matching import match_query_to_refs
from planarloc.geometry.camera import Camera
from planarloc.localize.local_structure import MapView, PairMatchCache, view_points
from planarloc.map.posed_image import PosedImage
from planarloc.map.store import MapDatabase
from planarloc.robust.pair_matches import PairMatches

#: The share of a query's 2D-3D constraints whose map images' disagreement with their poses sets
#: the query's map rotation std. A fifth: kitti_seq1 with the map every 8th frame, frames 1-5 take
#: about half their points from frame 0, whose pose is 2 px off (the median of the points' value
#: left frames 2 and 4 1.2 and 0.9 m off with stds of 0.22 and 0.19 m); one retrieved map image
#: far down the road with a bad pose gives fewer and must not widen the poses its neighbours fix
#: (the worst image's value did: position stds 0.04 -> 0.06 m from frame 13 on with the map every
#: 4th frame, and the 10 Hz stream without odometry posed 34-36 of 38 frames instead of 37).
MAP_DISAGREEMENT_SHARE = 0.2
COARSE_VIEWS_KEPT = 256
"""Map images whose coarse-pass features (views of their stored ones) a matcher keeps."""
DEPTH_MAPS_KEPT = 32
"""Map images whose depth maps a matcher keeps."""


@dataclass(frozen=True)
class MatchSettings:
    """The settings of one :meth:`MapMatcher.match` call.

    Attributes:
        ratio: the matcher's ratio test (:func:`~planarloc.features.matching.match_query_to_refs`).
        kind: the map's feature type (its matcher).
        min_matches: map images with fewer matches are left out.
        use_depth: the map images' depth maps give 3D points.
        structure: local structure (``tracks``): map keypoints triangulated between map images.
        threshold_px: the inlier threshold the local structure's triangulations are checked with.
        keypoint_std_px: the map images' keypoint noise (the points' covariance).
    """

    ratio: float
    kind: str
    min_matches: int
    use_depth: bool
    structure: bool
    threshold_px: float
    keypoint_std_px: float


@dataclass(frozen=True)
class QueryPairs:
    """What :meth:`MapMatcher.match` found.

    Attributes:
        pairs: one :class:`PairMatches` per map image with at least ``min_matches`` matches.
        names: their map images' names, in that order.
        disagreement: how much the map poses behind the query's 2D-3D constraints disagree with
            their images, ``(px, focal px)``: the largest disagreement that at least
            :data:`MAP_DISAGREEMENT_SHARE` of the constraints share (per constraint, the larger
            :attr:`~.local_structure.ViewPoints.pose_residual_px` of the two map images that
            triangulated it); ``(nan, nan)`` without structure.
    """

    pairs: list[PairMatches]
    names: list[str]
    disagreement: tuple[float, float]


def _partners_as_pairs(
    pairs: list[PairMatches], names: Sequence[str], references: Sequence[str]
) -> list[PairMatches]:
    """The local-structure partners of ``pairs`` (indices into ``references``) as the estimator
    takes them: an index into ``pairs`` (``names``), or ``len(pairs) + j`` for reference ``j``
    whose pair was dropped (its pose errors still move the points it triangulated)."""
    slot = {n: i for i, n in enumerate(names)}
    lookup = np.array([slot.get(n, len(names) + j) for j, n in enumerate(references)] + [-1], dtype=np.int64)
    return [
        p
        if p.ref_points3d_partner is None
        else replace(p, ref_points3d_partner=lookup[p.ref_points3d_partner])
        for p in pairs
    ]


class MapMatcher:
    """Matches queries with the images of one map; every configuration of a
    :class:`~planarloc.localize.localizer.Localizer` (its ``with_config``) shares one.

    Args:
        db: the open map.
        posed: its image records by name.
        g_world: (3,) the map's gravity direction in the world frame.
    """

    def __init__(self, db: MapDatabase, posed: Mapping[str, PosedImage], g_world: np.ndarray) -> None:
        self.db, self.posed, self.g_world = db, posed, g_world
        self.pair_cache = PairMatchCache()
        """Matches between map images (local structure) of all their keypoints, kept across queries."""
        self._coarse_pair_caches: dict[int, PairMatchCache] = {}  # the same, per coarse-pass budget
        self._coarse_views: OrderedDict[tuple[str, int], Features] = OrderedDict()
        self._depth_cache: OrderedDict[str, np.ndarray | None] = OrderedDict()
        self._lock = threading.Lock()  # a stream's fix worker and its caller may share a matcher

    def map_features(self, name: str, budget: int = 0) -> Features:
        """Map image ``name``'s stored features; with ``budget`` > 0 its first (strongest)
        ``budget`` (views, the same object for every query: the matcher's per-image caches hold)."""
        features = self.db.get_features(name)
        if budget <= 0 or len(features) <= budget:
            return features
        key = (name, budget)
        with self._lock:
            view = self._coarse_views.get(key)
            if view is None:
                view = features.first(budget)
                self._coarse_views[key] = view
                if len(self._coarse_views) > COARSE_VIEWS_KEPT:
                    self._coarse_views.popitem(last=False)
            else:
                self._coarse_views.move_to_end(key)
            return view

    def pair_cache_for(self, budget: int) -> PairMatchCache:
        """The local-structure cache of matches between map images of ``budget`` keypoints (0: all)."""
        if budget <= 0:
            return self.pair_cache
        with self._lock:
            return self._coarse_pair_caches.setdefault(budget, PairMatchCache())

    def view(self, name: str, features: Features) -> MapView:
        """What the local structure needs of map image ``name`` (:class:`MapView`): its
        ``features``, stored pose and camera."""
        posed = self.posed[name]
        return MapView(name, features, posed.cam_from_world, posed.camera)

    def _depth(self, name: str) -> np.ndarray | None:
        """Map image ``name``'s depth map in metres, None without one."""
        if name in self._depth_cache:
            return self._depth_cache[name]
        posed = self.posed[name]
        depth = None
        if posed.depth_path is not None:
            raw = cv2.imread(str(posed.depth_path), cv2.IMREAD_UNCHANGED)
            depth = None if raw is None else raw.astype(np.float32) / float(posed.depth_scale)
        self._depth_cache[name] = depth
        if len(self._depth_cache) > DEPTH_MAPS_KEPT:
            self._depth_cache.popitem(last=False)
        return depth

    def points3d(self, name: str, ref_points: np.ndarray) -> np.ndarray | None:
        """(N, 3) world points of map image ``name``'s (N, 2) pixels from its depth map (NaN rows
        without a depth); None without a depth map."""
        depth = self._depth(name)
        if depth is None:
            return None
        posed = self.posed[name]
        h, w = depth.shape[:2]
        uv = np.rint(ref_points).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        z = np.full(len(uv), np.nan)
        z[ok] = depth[uv[ok, 1], uv[ok, 0]]
        z[~(z > 0)] = np.nan
        X_cam = posed.camera.bearings_from_img(ref_points) * z[:, None]
        pose = posed.cam_from_world
        return (X_cam - pose.t) @ pose.R

    def match(
        self,
        features: Features,
        references: Sequence[str],
        camera: Camera | None,
        settings: MatchSettings,
        budget: int = 0,
    ) -> QueryPairs:
        """Match the query's ``features`` to each of ``references`` (map image names) and package
        the matches for the estimator (:class:`QueryPairs`). ``camera`` (the query's) lets
        keypoints outside its distortion model's range be dropped; ``budget`` > 0: the map images'
        first ``budget`` keypoints (the coarse pass; ``features`` are taken as given)."""
        refs = [self.map_features(n, budget) for n in references]
        matches = match_query_to_refs(features, refs, ratio=settings.ratio, kind=settings.kind)
        points3d = self._local_structure(references, refs, matches, settings, self.pair_cache_for(budget))
        view_residual = np.array([np.nan if p is None else p.pose_residual_px for p in points3d])
        point_residuals, focals = [], []
        pairs, names = [], []
        for name, ref, m, local in zip(references, refs, matches, points3d):
            if len(m) < settings.min_matches:
                continue
            posed = self.posed[name]
            # Keypoints outside the valid range of a distortion model cannot be undistorted.
            ok = np.isfinite(posed.camera.cam_from_img(ref.keypoints[m[:, 1]])).all(axis=1)
            if camera is not None:
                ok &= np.isfinite(camera.cam_from_img(features.keypoints[m[:, 0]])).all(axis=1)
            m = m[ok]
            if len(m) < settings.min_matches:
                continue
            ref_pts = np.asarray(ref.keypoints[m[:, 1]], dtype=float)
            X = self.points3d(name, ref_pts) if settings.use_depth else None
            cov = partner = jac = None
            if local is not None:
                X_local, cov, partner, jac = local.X[ok], local.cov[ok], local.partner[ok], local.pose_jac[ok]
                has = np.isfinite(X_local[:, 0]) & (partner >= 0)
                if has.any():
                    point_residuals.append(np.fmax(local.pose_residual_px, view_residual[partner[has]]))
                    focals.append(float(np.mean(posed.camera.focal)))
                if X is not None:  # measured depth first
                    take = np.isnan(X[:, 0])
                    X_local, cov = (
                        np.where(take[:, None], X_local, X),
                        np.where(take[:, None, None], cov, 0.0),
                    )
                    partner = np.where(take, partner, -1)
                X = X_local
            pairs.append(
                PairMatches(
                    posed.cam_from_world,
                    posed.camera,
                    np.asarray(features.keypoints[m[:, 0]], dtype=float),
                    ref_pts,
                    query_indices=m[:, 0],
                    ref_points3d=X,
                    ref_gravity=posed.cam_from_world.R @ self.g_world,
                    ref_points3d_cov=cov,
                    ref_points3d_partner=partner,
                    ref_points3d_pose_jac=jac,
                )
            )
            names.append(name)
        residuals = np.concatenate(point_residuals) if point_residuals else np.zeros(0)
        residuals = residuals[np.isfinite(residuals)]
        disagreement = (
            (float(np.quantile(residuals, 1.0 - MAP_DISAGREEMENT_SHARE)), float(np.mean(focals)))
            if len(residuals)
            else (np.nan, np.nan)
        )
        return QueryPairs(_partners_as_pairs(pairs, names, references), names, disagreement)

    def _local_structure(
        self,
        references: Sequence[str],
        refs: Sequence[Features],
        matches: Sequence[np.ndarray],
        settings: MatchSettings,
        cache: PairMatchCache,
    ) -> list:
        """Per reference, 3D points of its matched keypoints triangulated with the other
        references (:mod:`planarloc.localize.local_structure`), one per query keypoint (the
        widest angle over its matches); ``None`` per reference without structure mode."""
        if not settings.structure or len(references) < 2:
            return [None] * len(references)
        views = [self.view(n, f) for n, f in zip(references, refs)]
        points = view_points(
            views,
            [m[:, 1] for m in matches],
            cache,
            ratio=settings.ratio,
            max_error_px=settings.threshold_px,
            keypoint_std_px=settings.keypoint_std_px,
        )
        # One 2D-3D constraint per query keypoint: the widest-angle point among its matches.
        query_kp = np.concatenate([m[:, 0] for m in matches])
        angle = np.concatenate([np.where(p.partner >= 0, p.angle_deg, -1.0) for p in points])
        order = np.lexsort((-angle, query_kp))
        first = np.ones(len(order), dtype=bool)  # (no matches at all: nothing to keep)
        first[1:] = query_kp[order][1:] != query_kp[order][:-1]
        keep = np.zeros(len(query_kp), dtype=bool)
        keep[order[first]] = True
        keep &= angle >= 0
        start = 0
        for pts in points:
            drop = ~keep[start : start + len(pts.X)]
            pts.X[drop] = np.nan
            pts.cov[drop] = np.nan
            start += len(pts.X)
        return points
