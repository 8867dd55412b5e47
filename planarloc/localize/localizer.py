"""Localize query images against a map: retrieval, matching, robust absolute pose (paper Fig. 2).

The core works in memory on one live frame (:meth:`Localizer.localize`); nothing is written
to disk. Every front door prepares its input once with :meth:`Localizer.prepare` (image, camera
defaulting to the map's, gravity, references: :mod:`planarloc.localize.query`) and configures
with :func:`localizer_config` (one source of defaults).

Gravity: every reference gets ``ref_gravity = R_ref · g_world`` from the map's gravity
(:func:`planarloc.map.gravity.map_gravity`); a query's own gravity (an IMU's, in its
camera frame) is passed as ``gravity=``, otherwise the estimator assumes the query is mounted like
the map cameras (docs/conventions.md, "Gravity").
"""

from __future__ import annotations

import copy
import logging
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from planarloc.features.extract import Features, extract_features
from planarloc.features.matching import match_query_to_refs
from planarloc.features.retrieval import GlobalIndex, VladVocabulary, vlad_descriptor
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.localize.local_structure import MapView, PairMatchCache, map_rotation_std_deg, view_points
from planarloc.localize.localizer_config import MAP_PRIORS, LocalizerConfig, localizer_config  # noqa: F401  (re-exported)
from planarloc.localize.query import ImageSource, Query, prepare_query
from planarloc.map.gravity import map_gravity
from planarloc.map.pose_accuracy import load_accuracy
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import VOCABULARY_BLOB
from planarloc.map.settings import feature_config_from_map
from planarloc.map.std_calibration import load_std_calibration
from planarloc.map.store import MapDatabase
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.covisibility import epipolar_support, seeing_support
from planarloc.robust.options import RansacOptions, Structure
from planarloc.robust.pair_matches import PairMatches, unit_gravity
from planarloc.robust.result import PoseEstimate
from planarloc.robust.status import Status
from planarloc.robust.structure import KEYPOINT_STD_PX

logger = logging.getLogger(__name__)


#: The share of a query's 2D-3D constraints whose map images' disagreement with their poses sets
#: the query's map rotation std. A fifth: kitti_seq1 with the map every 8th frame, frames 1-5 take
#: about half their points from frame 0, whose pose is 2 px off (the median of the points' value
#: left frames 2 and 4 1.2 and 0.9 m off with stds of 0.22 and 0.19 m); one retrieved map image
#: far down the road with a bad pose gives fewer and must not widen the poses its neighbours fix
#: (the worst image's value did: position stds 0.04 -> 0.06 m from frame 13 on with the map every
#: 4th frame, and the 10 Hz stream without odometry posed 34-36 of 38 frames instead of 37).
MAP_DISAGREEMENT_SHARE = 0.2
MIN_KEYPOINT_STD_PX = 0.1
"""Floor of the measured keypoint noise of the map images (pixels)."""
CARRYING_3D_INLIERS = 30
"""A success with fewer 2D-3D inliers is judged under the configured map prior (not the measured one):
cross-session Strecha poses 0.2-0.33 m off with 19-27 2D-3D inliers had 0.08-0.11 m stds under the
measured one; entry -> fountain queries with 32 and 42 are 0.10-0.11 m off with stds of 0.17-0.22 m
(BENCHMARKS.md, the calibration row: 2 of 11, as the hloc-style peer)."""


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


class Localizer:
    """Localizes images against one map.

    Args:
        map_db: an open :class:`MapDatabase` or the path of a map file.
        config: :class:`LocalizerConfig`.

    Example:
        >>> loc = Localizer("office.db")                      # doctest: +SKIP
        >>> est = loc.localize(gray_image, camera)              # doctest: +SKIP
        >>> est.pose if est.success else est.status             # doctest: +SKIP
        >>> est = loc.localize(
        ...     gray_image, camera, gravity=(0.0, 0.99, 0.14)
        ... )  # IMU: pitched 8°  # doctest: +SKIP
    """

    def __init__(self, map_db: MapDatabase | str | Path, config: LocalizerConfig | None = None) -> None:
        self.db = map_db if isinstance(map_db, MapDatabase) else MapDatabase.open(map_db, mode="r")
        self.config = config or LocalizerConfig()
        if not self.db.is_complete:
            logger.warning("%s: the map build is not complete; localizing with what it holds", self.db.path)
        self.features = replace(feature_config_from_map(self.db), tilt=False)  # queries are not tilted
        blob = self.db.get_blob(VOCABULARY_BLOB)
        ids, descs = self.db.get_global_descriptors()
        if blob is None or len(ids) == 0:
            raise InputError(
                f"{self.db.path}: the map has no retrieval index; re-run `planarloc map build` on it"
            )
        self.vocabulary = VladVocabulary.from_bytes(blob)
        self.index_ids = ids
        self.index = GlobalIndex(descs, basis=self.db.global_basis())
        self._posed = {p.name: p for p in self.db.posed_images()}
        self._by_id = {self.db.image_id(n): n for n in self._posed}
        self._depth_cache: OrderedDict[str, np.ndarray | None] = OrderedDict()
        self.pair_cache = PairMatchCache()
        """Matches between map images (local structure), kept across queries."""
        self.gravity = map_gravity(self.db)
        """The map's :class:`~planarloc.gravity.world.GravityReport` (``g_world``, mount tilt)."""
        self.pose_accuracy = load_accuracy(self.db)
        """How well the map's poses agree with its images (:mod:`planarloc.map.pose_accuracy`),
        None for a map without the measurement."""
        self.std_calibration = load_std_calibration(self.db)
        """How the modelled std relates to the errors of the map's held-out images
        (:mod:`planarloc.map.std_calibration`), None for a map without the measurement."""
        self._g_world = self.gravity.g_world_array

    def with_config(self, config: LocalizerConfig) -> Localizer:
        """A localizer on the same open map, index and caches, with another configuration
        (e.g. one request's method and seed)."""
        other = copy.copy(self)
        other.config = config
        return other

    # ---- the map ------------------------------------------------------------------------
    @property
    def ransac_options(self) -> RansacOptions:
        """The estimator options queries use: ``config.ransac`` with the map pose prior taken from
        the map's measurement (:attr:`pose_accuracy`) when ``config.map_prior`` is ``"measured"``:
        as measured with structure (``tracks``), at least the configured one without; with
        structure, the map's std calibration (:attr:`std_calibration`) as ``std_scale``."""
        ransac, accuracy = self.config.ransac, self.pose_accuracy
        if self.config.map_prior != "measured" or accuracy is None:
            return ransac
        if ransac.structure != Structure.TRACKS:
            # 2D-2D constraints alone: the measurement may raise the assumed prior, never lower it
            # (a small prior does not make wrong-but-consistent matches precise; README, "map prior").
            return replace(
                ransac,
                map_rotation_std_deg=max(ransac.map_rotation_std_deg, accuracy.rotation_std_deg),
                map_position_std_m=max(ransac.map_position_std_m, accuracy.position_std_m),
            )
        return replace(
            ransac,
            map_rotation_std_deg=accuracy.rotation_std_deg,
            map_position_std_m=accuracy.position_std_m,
            map_prior_measured=True,
            assumed_map_prior=(ransac.map_rotation_std_deg, ransac.map_position_std_m),
            std_scale=self.std_calibration.scale if self.std_calibration is not None else ransac.std_scale,
        )

    @property
    def keypoint_std_px(self) -> float:
        """The map images' keypoint noise for the covariance of points triangulated from them:
        the map's measurement when ``config.map_prior`` is ``"measured"``, else
        :data:`~planarloc.robust.structure.KEYPOINT_STD_PX`."""
        accuracy = self.pose_accuracy
        if (
            self.config.map_prior != "measured"
            or accuracy is None
            or not np.isfinite(accuracy.keypoint_std_px)
        ):
            return KEYPOINT_STD_PX
        return max(float(accuracy.keypoint_std_px), MIN_KEYPOINT_STD_PX)

    @property
    def map_images(self) -> list[PosedImage]:
        """The map's image records (poses, cameras, files), in map order."""
        return list(self._posed.values())

    def map_view(self, name: str, features: Features) -> MapView:
        """What the local structure needs of map image ``name`` (:class:`MapView`): its
        ``features``, stored pose and camera."""
        posed = self._posed[name]
        return MapView(name, features, posed.cam_from_world, posed.camera)

    @property
    def map_cameras(self) -> set[Camera]:
        """The map's distinct cameras (a query without a camera takes the only one)."""
        return {p.camera for p in self._posed.values()}

    def prepare(
        self,
        image: ImageSource,
        camera: Camera | None = None,
        *,
        name: str = "query",
        gravity: object | None = None,
        references: Sequence[str] | None = None,
        pairs: Mapping[str, Sequence[str]] | None = None,
    ) -> Query:
        """Check and prepare one query against this map (:func:`planarloc.localize.query.prepare_query`).

        Args:
            image: (H, W) / (H, W, 3) BGR uint8 array, JPEG/PNG bytes or an image file.
            camera: the query's intrinsics; None: the map's (when it has exactly one camera).
            name: the query's name (looked up in ``pairs``).
            gravity: see :meth:`localize`.
            references: map images to match against instead of retrieval.
            pairs: hloc pairs ``{query name: [map names]}``: the first ``config.top_n`` of
                this query's are its references.
        """
        return prepare_query(
            image,
            camera,
            map_cameras=self.map_cameras,
            map_names=self._posed.keys(),
            name=name,
            gravity=gravity,
            references=references,
            pairs=pairs,
            top_n=self.config.top_n,
        )

    # ---- steps ---------------------------------------------------------------------------
    def retrieve(self, features: Features, top_n: int | None = None) -> list[str]:
        """Names of the ``top_n`` most similar map images (VLAD, cosine similarity)."""
        if len(features) == 0:
            return []
        idx, _ = self.index.search(
            vlad_descriptor(self.vocabulary, features.descriptors), top_n or self.config.top_n
        )
        return [self._by_id[int(self.index_ids[i])] for i in idx]

    def _depth(self, name: str) -> np.ndarray | None:
        if name in self._depth_cache:
            return self._depth_cache[name]
        posed = self._posed[name]
        depth = None
        if posed.depth_path is not None:
            raw = cv2.imread(str(posed.depth_path), cv2.IMREAD_UNCHANGED)
            depth = None if raw is None else raw.astype(np.float32) / float(posed.depth_scale)
        self._depth_cache[name] = depth
        if len(self._depth_cache) > 32:
            self._depth_cache.popitem(last=False)
        return depth

    def _points3d(self, name: str, ref_points: np.ndarray) -> np.ndarray | None:
        depth = self._depth(name)
        if depth is None:
            return None
        posed = self._posed[name]
        h, w = depth.shape[:2]
        uv = np.rint(ref_points).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        z = np.full(len(uv), np.nan)
        z[ok] = depth[uv[ok, 1], uv[ok, 0]]
        z[~(z > 0)] = np.nan
        X_cam = posed.camera.bearings_from_img(ref_points) * z[:, None]
        pose = posed.cam_from_world
        return (X_cam - pose.t) @ pose.R

    def pairs_for(
        self, features: Features, references: Sequence[str], camera: Camera | None = None
    ) -> tuple[list[PairMatches], list[str]]:
        """Match the query to each reference and package the matches for the estimator.

        ``camera`` (the query's) lets keypoints outside its distortion model's range be dropped.

        Returns:
            the pairs with at least ``min_matches`` matches, and the names of their references.
        """
        pairs, names, _ = self._pairs_and_map_residual(features, references, camera)
        return pairs, names

    def _pairs_and_map_residual(
        self, features: Features, references: Sequence[str], camera: Camera | None
    ) -> tuple[list[PairMatches], list[str], tuple[float, float]]:
        """:meth:`pairs_for`, and how much the map poses behind the query's 2D-3D constraints
        disagree with their images: ``(px, focal px)``, the largest disagreement that at least
        :data:`MAP_DISAGREEMENT_SHARE` of the constraints share (per constraint, the larger
        :attr:`ViewPoints.pose_residual_px` of the two map images that triangulated it; NaN, NaN
        without structure)."""
        refs = [self.db.get_features(n) for n in references]
        matches = match_query_to_refs(features, refs, ratio=self.config.ratio, kind=self.features.kind)
        points3d = self._local_structure(references, refs, matches)
        view_residual = np.array([np.nan if p is None else p.pose_residual_px for p in points3d])
        point_residuals, focals = [], []
        pairs, names = [], []
        for name, ref, m, local in zip(references, refs, matches, points3d):
            if len(m) < self.config.min_matches:
                continue
            posed = self._posed[name]
            # Keypoints outside the valid range of a distortion model cannot be undistorted.
            ok = np.isfinite(posed.camera.cam_from_img(ref.keypoints[m[:, 1]])).all(axis=1)
            if camera is not None:
                ok &= np.isfinite(camera.cam_from_img(features.keypoints[m[:, 0]])).all(axis=1)
            m = m[ok]
            if len(m) < self.config.min_matches:
                continue
            ref_pts = np.asarray(ref.keypoints[m[:, 1]], dtype=float)
            X = self._points3d(name, ref_pts) if self.config.use_depth else None
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
                    ref_gravity=posed.cam_from_world.R @ self._g_world,
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
        return _partners_as_pairs(pairs, names, references), names, disagreement

    def _local_structure(
        self, references: Sequence[str], refs: Sequence[Features], matches: Sequence[np.ndarray]
    ) -> list:
        """Per reference, 3D points of its matched keypoints triangulated with the other
        references (:mod:`planarloc.localize.local_structure`), one per query keypoint (the
        widest angle over its matches); ``None`` per reference without structure mode."""
        if self.config.ransac.structure != Structure.TRACKS or len(references) < 2:
            return [None] * len(references)
        views = [self.map_view(n, f) for n, f in zip(references, refs)]
        points = view_points(
            views,
            [m[:, 1] for m in matches],
            self.pair_cache,
            ratio=self.config.ratio,
            max_error_px=self.config.ransac.threshold_px,
            keypoint_std_px=self.keypoint_std_px,
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

    def warm_up(self) -> float:
        """Localize one map image's stored features against the other retrieved map images and
        discard the answer; returns the seconds it took.

        A process's first query pays once for loading the compiled kernels from numba's cache
        (or compiling them on first use), for first calls into OpenCV and faiss and for the
        local-structure matches between map images (kept in :attr:`pair_cache`): ~1 s with a
        warm compile cache against ~0.1 s for the next queries. A live front door (the ROS 2
        node) calls this before it takes frames, so that its first frame is not the slow one.
        """
        t0 = time.perf_counter()
        names = list(self._posed)
        if len(names) < 2:
            return 0.0
        name = names[len(names) // 2]
        features = self.db.get_features(name)
        references = [r for r in self.retrieve(features, self.config.top_n + 1) if r != name][
            : self.config.top_n
        ]
        if len(features) and len(references) >= 2:
            est = self.localize_features(features, self._posed[name].camera, references)
            logger.debug("warm-up on map image %s: %s", name, est.status)
        return time.perf_counter() - t0

    # ---- whole pipeline ------------------------------------------------------------------
    def localize_features(
        self,
        features: Features,
        camera: Camera,
        references: Sequence[str] | None = None,
        *,
        gravity: object | None = None,
    ) -> PoseEstimate:
        """Localize from already extracted query features (retrieval unless ``references``).

        ``gravity``: see :meth:`localize`.
        """
        return self.localize_pairs(features, camera, references, gravity=gravity)[0]

    def localize_pairs(
        self,
        features: Features,
        camera: Camera,
        references: Sequence[str] | None = None,
        *,
        gravity: object | None = None,
    ) -> tuple[PoseEstimate, list[PairMatches]]:
        """:meth:`localize_features`, and the matched pairs it estimated from (one per name of
        ``est.references``, in that order, as ``est.inliers``): callers that need the inliers'
        matches (the stream's tracked map points) need not match again."""
        t0 = time.perf_counter()
        query_gravity = None if gravity is None else unit_gravity("gravity", gravity)
        refs = list(references) if references is not None else self.retrieve(features)
        unknown = [r for r in refs if r not in self._posed]
        if unknown:
            raise InputError(f"references not in the map: {unknown[:3]}{'...' if len(unknown) > 3 else ''}")
        if len(features) < self.config.min_matches:  # a black, uniform or blurred frame: nothing to match
            est = PoseEstimate(
                None,
                False,
                Status.TOO_FEW_MATCHES,
                f"the image has {len(features)} features (a black, uniform or featureless frame): "
                "nothing to match with the map",
                [],
            )
            est.stats.add_time("retrieval", time.perf_counter() - t0)
            return est, []
        t1 = time.perf_counter()
        pairs, used, (residual_px, focal_px) = self._pairs_and_map_residual(features, refs, camera)
        t2 = time.perf_counter()
        if len(pairs) < 2:
            est = PoseEstimate(
                None,
                False,
                Status.TOO_FEW_MATCHES,
                f"fewer than 2 of the {len(refs)} retrieved map images have >= "
                f"{self.config.min_matches} matches",
                [np.zeros(0, bool)] * len(pairs),
            )
        else:
            # Map poses that disagree with their images (KITTI's first seconds) move every point
            # triangulated from them together: the map prior takes what the images measured.
            ransac = map_wide = self.ransac_options
            measured = map_rotation_std_deg(residual_px, focal_px)
            if measured > ransac.map_rotation_std_deg:
                # Not the regime the map's std calibration measured: the model's own std.
                ransac = replace(ransac, map_rotation_std_deg=measured, std_scale=1.0)
            est = estimate_absolute_pose(
                camera, pairs, self.config.method, ransac, query_gravity=query_gravity
            )
            est.map_prior = (ransac.map_rotation_std_deg, ransac.map_position_std_m)
            if ransac is not map_wide:
                est.message += (
                    f"; the retrieved map images' poses disagree with their images by {residual_px:.1f} px "
                    f"(median): map rotation std taken as {measured:.2f}° instead of "
                    f"{map_wide.map_rotation_std_deg:.2g}°"
                )
            if ransac.map_prior_measured and est.success and est.num_inliers_3d < CARRYING_3D_INLIERS:
                return self._under_assumed_prior(features, camera, refs, query_gravity, est.num_inliers_3d)
            if ransac.map_prior_measured and est.success and ransac.std_scale != 1.0:
                est.message += (
                    f"; modelled position std x {ransac.std_scale:.2g}, as the map's held-out images "
                    "measured (planarloc map info)"
                )
        if not est.success:  # any failure: whether a map image sees the query at all decides the advice
            t3 = time.perf_counter()
            est = self._unless_unseen(est, refs, pairs, camera)
            est.stats.add_time("covisibility", time.perf_counter() - t3)
        est.references = used
        est.stats.add_time("retrieval", t1 - t0)
        est.stats.add_time("matching", t2 - t1)
        return est, pairs

    def _under_assumed_prior(
        self, features: Features, camera: Camera, refs: Sequence[str], gravity: np.ndarray | None, num_3d: int
    ) -> tuple[PoseEstimate, list[PairMatches]]:
        """The estimate of a pose that few 2D-3D inliers carry, judged again under the configured
        (assumed) map prior and keypoint noise: the measured ones, small on a well-posed map, say
        how precise points triangulated from it are, not that a query mostly matched 2D-2D is
        (:data:`CARRYING_3D_INLIERS`)."""
        est, pairs = self.with_config(replace(self.config, map_prior="configured")).localize_pairs(
            features, camera, refs, gravity=gravity
        )
        est.message += (
            f"; judged under the configured map prior: only {num_3d} 2D-3D inliers (fewer than "
            f"{CARRYING_3D_INLIERS}) carry the pose"
        )
        return est, pairs

    def _unless_unseen(
        self, est: PoseEstimate, refs: Sequence[str], pairs: Sequence[PairMatches], camera: Camera
    ) -> PoseEstimate:
        """``est``, or ``not_in_map`` when no retrieved map image sees the query
        (:mod:`planarloc.robust.covisibility`): the message says what was tried and keeps the
        estimator's own reason."""
        threshold = self.config.ransac.threshold_px
        support = [
            epipolar_support(p.query_points, p.ref_points, camera, p.ref_camera, threshold) for p in pairs
        ]
        needed = [seeing_support(len(p.query_points)) for p in pairs]
        if any(s >= n for s, n in zip(support, needed)):
            return est
        shown = ", ".join(refs[:3]) + (f" and {len(refs) - 3} more" if len(refs) > 3 else "")
        tried = (
            (
                f"{len(pairs)} of them have >= {self.config.min_matches} matches, and at most "
                f"{max(support, default=0)} matches of one image fit one essential matrix ({min(needed)} or "
                "more would show it sees the query)"
            )
            if pairs
            else f"none of them has {self.config.min_matches} or more matches"
        )
        before = f"{est.status}: {est.message}" if est.message else str(est.status)
        est.status = Status.NOT_IN_MAP
        est.message = (
            f"no map image sees the query: tried {len(refs)} map images ({shown}); {tried}. "
            "The map does not hold this place (or it looks too different now): map it, or localize where "
            f"the map was recorded (the estimator said {before})"
        )
        return est

    def localize(
        self,
        image: ImageSource,
        camera: Camera | None = None,
        references: Sequence[str] | None = None,
        *,
        gravity: object | None = None,
    ) -> PoseEstimate:
        """Localize one live frame taken with ``camera``.

        Args:
            image: (H, W) or (H, W, 3) BGR uint8 array (or JPEG/PNG bytes, or a file).
            camera: the query's intrinsics; None: the map's, when the map has exactly one camera.
            references: map image names to match against instead of retrieval.
            gravity: (3,) direction of gravity (pointing down) in the query camera frame
                (x right, y down, z forward), e.g. an IMU's accelerometer reading negated
                (it measures the reaction, i.e. up) and rotated into the camera frame; any
                non-zero length. None: the query is assumed mounted like the map cameras.

        Returns:
            the estimate; a frame with nothing to match (black, uniform, featureless) is a failed
            one with status ``"too_few_matches"`` and a message saying so.

        Raises:
            InputError: an empty, truncated, damaged or oversized image (over
                :data:`~planarloc.features.images.MAX_IMAGE_PIXELS`), a camera of another size, a
                bad gravity (:mod:`planarloc.localize.query`).
        """
        t0 = time.perf_counter()
        return self.localize_query(self.prepare(image, camera, gravity=gravity, references=references), t0)

    def localize_query(self, query: Query, started: float | None = None) -> PoseEstimate:
        """Localize a prepared query (:meth:`prepare`); ``started``: its ``time.perf_counter()``
        start, when preparing it counts in the end-to-end time."""
        t0 = time.perf_counter() if started is None else started
        t_features = time.perf_counter()
        features = extract_features(query.image, self.features)
        est = self.localize_features(features, query.camera, query.references, gravity=query.gravity)
        est.stats.add_time(
            "features",
            time.perf_counter()
            - t_features
            - sum(est.stats.time_s.get(k, 0.0) for k in ("retrieval", "matching", "total")),
        )
        est.stats.time_s["end_to_end"] = time.perf_counter() - t0
        return est
