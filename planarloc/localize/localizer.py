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
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from planarloc.features.extract import Features, extract_features
from planarloc.features.registry import feature_type
from planarloc.features.retrieval import GlobalIndex, VladVocabulary, vlad_descriptor
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.localize.local_structure import MapView, PairMatchCache, map_rotation_std_deg
from planarloc.localize.localizer_config import MAP_PRIORS, LocalizerConfig, localizer_config  # noqa: F401  (re-exported)
from planarloc.localize.query import ImageSource, Query, prepare_query
from planarloc.localize.query_matches import MapMatcher, MatchSettings
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


MIN_KEYPOINT_STD_PX = 0.1
"""Floor of the measured keypoint noise of the map images (pixels)."""
CARRYING_3D_INLIERS = 30
"""A success with fewer 2D-3D inliers is judged under the configured map prior (not the measured one):
cross-session Strecha poses 0.2-0.33 m off with 19-27 2D-3D inliers had 0.08-0.11 m stds under the
measured one; entry -> fountain queries with 32 and 42 are 0.10-0.11 m off with stds of 0.17-0.22 m
(BENCHMARKS.md, the calibration row: 2 of 11, as the hloc-style peer)."""


def _joined(message: str, more: str) -> str:
    """``message; more`` (``more`` alone when there is no message)."""
    return f"{message}; {more}" if message else more


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
        self.gravity = map_gravity(self.db)
        """The map's :class:`~planarloc.gravity.world.GravityReport` (``g_world``, mount tilt)."""
        self.pose_accuracy = load_accuracy(self.db)
        """How well the map's poses agree with its images (:mod:`planarloc.map.pose_accuracy`),
        None for a map without the measurement."""
        self.std_calibration = load_std_calibration(self.db)
        """How the modelled std relates to the errors of the map's held-out images
        (:mod:`planarloc.map.std_calibration`), None for a map without the measurement."""
        self._g_world = self.gravity.g_world_array
        self.matcher = MapMatcher(self.db, self._posed, self._g_world)
        """Matches queries with the map images (:mod:`planarloc.localize.query_matches`), its caches
        shared by every :meth:`with_config`."""

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

    @property
    def coarse_keypoints(self) -> int:
        """How many strongest keypoints a query's coarse pass uses (0: no coarse pass):
        ``config.coarse_keypoints``, else the map's feature type's
        (:attr:`~planarloc.features.registry.FeatureType.coarse_keypoints`) with local structure
        (``tracks``) and none without: on 2D-2D constraints alone, XFeat's coarse pass broke 2
        promises in 240-246 successes (generated worlds with pitched cameras or tilted floors,
        0.29-0.60 m off at 4.4-6.7 stds; every keypoint: 0 in 238), with local structure 0 in
        377 (BENCHMARKS.md, "The coarse pass")."""
        n = self.config.coarse_keypoints
        if n is not None:
            return n
        if self.config.ransac.structure != Structure.TRACKS:
            return 0
        return int(feature_type(self.features.kind).coarse_keypoints or 0)

    @property
    def pair_cache(self) -> PairMatchCache:
        """Matches between map images (local structure), kept across queries."""
        return self.matcher.pair_cache

    def map_features(self, name: str, budget: int = 0) -> Features:
        """Map image ``name``'s stored features, or their first (strongest) ``budget`` if > 0."""
        return self.matcher.map_features(name, budget)

    def map_view(self, name: str, features: Features) -> MapView:
        """What the local structure needs of map image ``name`` (:class:`MapView`): its
        ``features``, stored pose and camera."""
        return self.matcher.view(name, features)

    def match_settings(self) -> MatchSettings:
        """The settings of this configuration's matching (:class:`~.query_matches.MatchSettings`)."""
        return MatchSettings(
            ratio=self.config.ratio,
            kind=self.features.kind,
            min_matches=self.config.min_matches,
            use_depth=self.config.use_depth,
            structure=self.config.ransac.structure == Structure.TRACKS,
            threshold_px=self.config.ransac.threshold_px,
            keypoint_std_px=self.keypoint_std_px,
        )

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

    def pairs_for(
        self,
        features: Features,
        references: Sequence[str],
        camera: Camera | None = None,
        *,
        keypoint_budget: int = 0,
    ) -> tuple[list[PairMatches], list[str]]:
        """Match the query to each reference and package the matches for the estimator.

        ``camera`` (the query's) lets keypoints outside its distortion model's range be dropped.
        ``keypoint_budget`` > 0: the first (strongest) that many keypoints of the query and of each
        reference, as an estimate's :attr:`~planarloc.robust.result.PoseEstimate.keypoint_budget`
        says it used.

        Returns:
            the pairs with at least ``min_matches`` matches, and the names of their references.
        """
        if keypoint_budget > 0:
            features = features.first(keypoint_budget)
        found = self.matcher.match(features, references, camera, self.match_settings(), keypoint_budget)
        return found.pairs, found.names

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
        matches (the stream's tracked map points) need not match again.

        With :attr:`coarse_keypoints` > 0 and a query of more keypoints, the coarse pass comes
        first: the query's strongest :attr:`coarse_keypoints` against as many of each of the
        first ``config.coarse_top_n`` references'. Its success is the answer
        (``est.keypoint_budget`` says so); otherwise every keypoint is matched against every
        reference, and the estimate's statistics count both passes."""
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
        retrieval_s = time.perf_counter() - t0
        budget = self.coarse_keypoints
        coarse = None
        if 0 < budget < len(features):
            nearest = refs[: self.config.coarse_top_n]
            coarse, pairs = self._estimate(features.first(budget), camera, nearest, query_gravity, budget)
            if coarse.success:
                ranked = feature_type(self.features.kind).coarse_keypoints is not None
                coarse.message = _joined(
                    coarse.message,
                    f"from the {budget} {'strongest' if ranked else 'first'} of the query's {len(features)} "
                    f"keypoints and of each of the first {len(nearest)} map images' (the coarse pass)",
                )
                coarse.stats.add_time("retrieval", retrieval_s)
                return coarse, pairs
        est, pairs = self._estimate(features, camera, refs, query_gravity, 0)
        if coarse is not None:
            est.stats.merge(coarse.stats)
            est.message = _joined(
                est.message,
                f"from all {len(features)} keypoints: the coarse pass of {budget} gave {coarse.status}",
            )
        est.stats.add_time("retrieval", retrieval_s)
        return est, pairs

    def _estimate(
        self,
        features: Features,
        camera: Camera,
        refs: Sequence[str],
        query_gravity: np.ndarray | None,
        budget: int,
    ) -> tuple[PoseEstimate, list[PairMatches]]:
        """One pass of :meth:`localize_pairs` on ``refs``: match (the map images' first ``budget``
        keypoints if > 0, ``features`` as given), estimate, judge."""
        t1 = time.perf_counter()
        found = self.matcher.match(features, refs, camera, self.match_settings(), budget)
        pairs, used, (residual_px, focal_px) = found.pairs, found.names, found.disagreement
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
                num_3d = est.num_inliers_3d
                return self._under_assumed_prior(features, camera, refs, query_gravity, num_3d, budget)
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
        est.keypoint_budget = budget
        est.stats.add_time("matching", t2 - t1)
        return est, pairs

    def _under_assumed_prior(
        self,
        features: Features,
        camera: Camera,
        refs: Sequence[str],
        gravity: np.ndarray | None,
        num_3d: int,
        budget: int,
    ) -> tuple[PoseEstimate, list[PairMatches]]:
        """The estimate of a pose that few 2D-3D inliers carry, judged again under the configured
        (assumed) map prior and keypoint noise: the measured ones, small on a well-posed map, say
        how precise points triangulated from it are, not that a query mostly matched 2D-2D is
        (:data:`CARRYING_3D_INLIERS`)."""
        est, pairs = self.with_config(replace(self.config, map_prior="configured"))._estimate(
            features, camera, refs, gravity, budget
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
