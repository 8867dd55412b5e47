"""Do images to be appended share the map's world frame? The check before a build appends them.

Poses are only comparable within one world frame. Two datasets whose poses are each relative to
their own first camera (KITTI sequences, most SLAM exports) are in two unrelated frames that both
start at the origin: appending one to a map of the other silently puts two roads in one world,
and nothing in the poses tells. The images do. Two images of the same place, posed in the same
frame, share feature matches, and those matches obey the epipolar geometry of their *known*
relative pose ``map_from_appended = cam_from_world_map · cam_from_world_appended.inverse()``. In an
unrelated frame they either share no matches at all (another place) or their matches contradict
the known relative pose (the same place, posed in another frame).

:func:`check_appended_frames`, run by :func:`planarloc.map.builder.build_map` before it appends
images to a non-empty map:

1. picks at most ``max_images`` of the appended images: those whose claimed camera centres are
   nearest to a map camera (:func:`nearest_first`); in the map's frame, they should see what the
   map sees;
2. pairs each with a few map images: the most similar ones by the map's retrieval index (VLAD,
   :mod:`planarloc.features.retrieval`) and the nearest ones by claimed camera centre;
3. matches their local features (:func:`planarloc.features.matching.match_features`) and counts
   per pair (:func:`pair_support`) the **shared** matches, the inliers of a freely estimated
   relative pose (5-point RANSAC, :func:`planarloc.robust.relative_pose.estimate_relative_pose`),
   and the **agreeing** matches, those within ``pose_threshold_px`` of the known relative pose
   (:func:`known_pose_errors_px`);
4. a pair with at least ``min_shared`` shared matches *agrees* when the known pose explains at
   least ``min_agreement`` times as many matches as the free estimate, else it *contradicts*
   (:func:`pair_verdict`).

The appended images are related to the map (:func:`frames_related`) when at least one pair agrees
and at most half as many pairs contradict. The check stops early once ``enough_agreeing`` pairs
agree (and the verdict is "related"); in an unrelated frame it matches at most ``max_images`` ·
(``retrieved`` + ``nearest``) pairs, with at most ``max_features`` features per image.

Measured on KITTI (``kitti_seq2``, a map of its 26 even frames, 4000 RootSIFT each): appending
the odd frames, one image and 4 pairs are checked and all agree (e.g. 550 shared matches, 555
agree); appending ``kitti_seq1`` (another road, also "first camera frame"), 10 images and 40 pairs,
none shares matches (at most 29 descriptor matches in a pair); the odd frames with their poses
turned by 1° about the world's vertical axis, or moved by 3 m, contradict (e.g. 456 shared
matches, 28 agree; 287 shared, 42 agree).

Limits: appended images that see nothing of the map (another place in the same, e.g.
georeferenced, frame) cannot be checked and count as unrelated. Two-view geometry has no scale:
a pure offset along the direction of travel looks like other spacings of the same images, so an
offset without a rotation is caught only when it is large or across that direction (1 m on KITTI
passes, 3 m does not).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from planarloc.features.extract import Features
from planarloc.features.matching import match_features
from planarloc.features.retrieval import GlobalIndex, VladVocabulary, vlad_descriptor
from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import essential_from_relpose, sampson_error_sq
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array, check_integer, check_positive
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import VOCABULARY_BLOB
from planarloc.map.store import MapDatabase
from planarloc.robust.options import RansacOptions
from planarloc.robust.relative_pose import estimate_relative_pose

logger = logging.getLogger(__name__)

#: A relative translation shorter than this (world units) is no baseline: the known pose is a
#: pure rotation and is checked as one (:func:`known_pose_errors_px`).
MIN_BASELINE = 1e-6

Verdict = Literal["agrees", "contradicts", "unmatched"]
#: ``extract(image)``: the local features of an appended image, or why it cannot be read (a string).
Extract = Callable[[PosedImage], "Features | str"]
#: ``mapper(fn, images)`` -> ``fn(image)`` for each image, in order (like the builtin ``map``).
Mapper = Callable[[Extract, Sequence[PosedImage]], Iterable["Features | str"]]


class UnrelatedFramesError(InputError):
    """A build would append images whose world frame is unrelated to the map's."""


@dataclass(frozen=True)
class FrameCheckOptions:
    """Settings of :func:`check_appended_frames`.

    Attributes:
        max_images: appended images checked at most (the nearest to the map's cameras).
        retrieved: map images per appended image from the retrieval index (VLAD).
        nearest: map images per appended image by claimed camera centre.
        max_features: features per image used for matching (an evenly spread subset above it).
        threshold_px: inlier threshold (Sampson error, pixels) of the free relative pose.
        pose_threshold_px: a match agrees with the known relative pose when its error under it
            (:func:`known_pose_errors_px`) is below this (pixels); looser than ``threshold_px``
            because map poses carry errors (0.5° of rotation is about 6 px at f = 700 px).
        min_shared: a pair shares matches when the free relative pose has this many inliers.
        min_agreement: a pair that shares matches agrees when the known pose explains at least
            this fraction of the free pose's inlier count.
        enough_agreeing: the check stops once this many pairs agree.
        seed: seeds the RANSAC of the free relative pose.
    """

    max_images: int = 10
    retrieved: int = 2
    nearest: int = 2
    max_features: int = 2000
    threshold_px: float = 2.0
    pose_threshold_px: float = 6.0
    min_shared: int = 30
    min_agreement: float = 0.8
    enough_agreeing: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("max_images", "retrieved", "nearest", "max_features", "min_shared", "enough_agreeing"):
            check_integer(f"FrameCheckOptions.{name}", getattr(self, name), 1 if name != "retrieved" else 0)
        check_integer("FrameCheckOptions.seed", self.seed, 0)
        for name in ("threshold_px", "pose_threshold_px", "min_agreement"):
            check_positive(f"FrameCheckOptions.{name}", getattr(self, name))


DEFAULT_FRAME_CHECK = FrameCheckOptions()


@dataclass(frozen=True)
class PairEvidence:
    """What one (appended image, map image) pair says about the frames.

    Attributes:
        appended, map_image: the two image names.
        matches: descriptor matches.
        shared: inliers of the freely estimated relative pose.
        agreeing: matches within ``pose_threshold_px`` of the known relative pose.
        verdict: ``"agrees"``, ``"contradicts"`` or ``"unmatched"`` (:func:`pair_verdict`).
    """

    appended: str
    map_image: str
    matches: int
    shared: int
    agreeing: int
    verdict: Verdict


@dataclass
class FrameCheck:
    """Result of :func:`check_appended_frames`.

    Attributes:
        checked: names of the appended images that were matched against the map.
        pairs: the evidence of every matched pair, in the order matched.
        related: the appended images share the map's world frame (:func:`frames_related`).
        seconds: time the check took.
        options: the settings it was made with.
    """

    checked: list[str] = field(default_factory=list)
    pairs: list[PairEvidence] = field(default_factory=list)
    related: bool = True
    seconds: float = 0.0
    options: FrameCheckOptions = DEFAULT_FRAME_CHECK

    def count(self, verdict: Verdict) -> int:
        return sum(p.verdict == verdict for p in self.pairs)

    def summary(self) -> str:
        """What was found, in one line (no trailing period)."""
        agree, contra = self.count("agrees"), self.count("contradicts")
        head = (
            f"{len(self.checked)} of them checked against {len({p.map_image for p in self.pairs})} map images"
        )
        if contra:
            worst = min(
                (p for p in self.pairs if p.verdict == "contradicts"), key=lambda p: p.agreeing / p.shared
            )
            return (
                f"{head}: {contra} pair(s) share matches that contradict the images' poses (e.g. "
                f"{worst.appended} and {worst.map_image}: {worst.shared} shared matches, {worst.agreeing} "
                f"agree with their poses), {agree} pair(s) agree"
            )
        if agree:
            return f"{head}: {agree} pair(s) share matches that agree with the images' poses"
        if not self.pairs:
            return f"{head}: no pair to match"
        return (
            f"{head}: no pair shares matches (at most {max(p.matches for p in self.pairs)} descriptor "
            f"matches and {max(p.shared for p in self.pairs)} geometrically consistent ones in a pair, "
            f"{self.options.min_shared} needed)"
        )


def pair_verdict(shared: int, agreeing: int, options: FrameCheckOptions = DEFAULT_FRAME_CHECK) -> Verdict:
    """``"unmatched"`` below ``min_shared`` shared matches; else ``"agrees"`` when
    ``agreeing >= min_agreement · shared``, else ``"contradicts"``."""
    if shared < options.min_shared:
        return "unmatched"
    return "agrees" if agreeing >= options.min_agreement * shared else "contradicts"


def frames_related(verdicts: Sequence[Verdict]) -> bool:
    """True when at least one pair agrees and at most half as many pairs contradict."""
    agree = sum(v == "agrees" for v in verdicts)
    return agree >= 1 and 2 * sum(v == "contradicts" for v in verdicts) <= agree


def known_pose_errors_px(
    R: np.ndarray,
    t: np.ndarray,
    x_a: np.ndarray,
    x_b: np.ndarray,
    f_a: np.ndarray | tuple[float, float],
    f_b: np.ndarray | tuple[float, float],
) -> np.ndarray:
    """Pixel error of each ray pair under a known relative pose ``b_from_a = (R, t)``.

    A point seen along ray ``x_a`` at depth λ > 0 appears in image b at ``π(R x_a + t / λ)``: on the
    epipolar line, on the half-line that starts at the image of its point at infinity ``π(R x_a)``
    (λ → ∞) and heads for the epipole ``π(t)`` (λ → 0), direction
    ``v = t_xy − π(R x_a) t_z``. The error is the larger of

    - the Sampson error of ``x_bᵀ [t]x R x_a = 0``
      (:func:`planarloc.geometry.epipolar.sampson_error_sq`, in pixels with the focal lengths),
    - how far ``x_b`` lies behind ``π(R x_a)`` along ``v``, in pixels of image b: a match on the
      epipolar line but on its other half would need a point behind the cameras (the sign of
      ``t``, which ``E`` does not see). Not tested where ``R x_a`` points away from camera b.

    For a translation shorter than :data:`MIN_BASELINE` (no epipolar geometry) it is the distance
    in image b between ``x_b`` and ``π(R x_a)`` (infinite where ``R x_a`` points away from camera b).

    Args:
        R: (3, 3) rotation of ``b_from_a``.
        t: (3,) translation of ``b_from_a``, world units.
        x_a, x_b: (N, 3) normalized homogeneous points ``(x, y, 1)`` of cameras a and b.
        f_a, f_b: (fx, fy) focal lengths of the two cameras, pixels.

    Returns:
        (N,) errors in pixels.

    References:
        Hartley & Zisserman, Multiple View Geometry, 2nd ed., eq. 11.9 (Sampson error) and
        Sec. 9.2.2 (the epipolar line as the image of the ray).

    Example:
        >>> x = np.array([[0.1, -0.2, 1.0]])
        >>> known_pose_errors_px(np.eye(3), np.zeros(3), x, x, (500, 500), (500, 500)).tolist()
        [0.0]
        >>> t = np.array([0.0, 0.0, 1.0])   # b is 1 m behind a: points move towards the centre
        >>> float(known_pose_errors_px(np.eye(3), t, x, 0.5 * x + [0, 0, 0.5], (500, 500), (500, 500))[0])
        0.0
        >>> err = known_pose_errors_px(np.eye(3), -t, x, 0.5 * x + [0, 0, 0.5], (500, 500), (500, 500))
        >>> round(float(err[0]), 1)
        55.9
    """
    R = check_array("R", R, (3, 3))
    t = check_array("t", t, (3,))
    x_a = check_array("x_a", x_a, (None, 3))
    x_b = check_array("x_b", x_b, (len(x_a), 3))
    f_b = np.asarray(f_b, dtype=float)
    a = x_a @ R.T  # (N, 3): the rays of a in camera b's axes
    ahead = a[:, 2] > 0
    inf_px = np.zeros((len(a), 2))  # π(R x_a) and x_b, pixels of image b (without the principal point)
    inf_px[ahead] = a[ahead, :2] / a[ahead, 2:3] * f_b
    b_px = x_b[:, :2] / x_b[:, 2:3] * f_b
    norm = float(np.linalg.norm(t))
    if norm < MIN_BASELINE:
        out = np.full(len(a), np.inf)
        out[ahead] = np.linalg.norm(b_px[ahead] - inf_px[ahead], axis=1)
        return out
    t = t / norm
    sampson = np.sqrt(sampson_error_sq(essential_from_relpose(R, t), x_a, x_b, f_a, f_b))
    v = (t[:2] - inf_px / f_b * t[2]) * f_b  # (N, 2) direction from π(R x_a) to the epipole, pixels
    length = np.linalg.norm(v, axis=1)
    test = ahead & (length > 1e-12)
    behind = np.zeros(len(a))
    behind[test] = -np.einsum("ij,ij->i", b_px[test] - inf_px[test], v[test]) / length[test]
    return np.maximum(sampson, np.maximum(behind, 0.0))


def pair_support(
    camera_a: Camera,
    camera_b: Camera,
    b_from_a: Pose,
    points_a: object,
    points_b: object,
    options: FrameCheckOptions = DEFAULT_FRAME_CHECK,
) -> tuple[int, int]:
    """``(shared, agreeing)`` of N pixel matches between images a and b with known poses.

    Args:
        camera_a, camera_b: intrinsics of the two images.
        b_from_a: the relative pose the two images' poses claim,
            ``cam_from_world_b · cam_from_world_a.inverse()``.
        points_a, points_b: (N, 2) matching pixels.
        options: thresholds (``threshold_px``, ``pose_threshold_px``) and the RANSAC seed.

    Returns:
        ``shared``: inliers of the relative pose estimated from the matches alone (6DoF,
        5-point RANSAC, Sampson error below ``threshold_px``); ``agreeing``: matches whose error
        under ``b_from_a`` (:func:`known_pose_errors_px`) is below ``pose_threshold_px``. Pixels
        outside a camera's model count for neither.
    """
    pa = check_array("points_a", points_a, (None, 2))
    pb = check_array("points_b", points_b, (len(pa), 2))
    xa, xb = camera_a.bearings_from_img(pa), camera_b.bearings_from_img(pb)
    ok = np.isfinite(xa).all(axis=1) & np.isfinite(xb).all(axis=1)
    if ok.sum() < 5:
        return 0, 0
    ransac = RansacOptions(
        threshold_px=options.threshold_px, min_iterations=50, max_iterations=300, seed=options.seed
    )
    est = estimate_relative_pose(
        camera_a, camera_b, pa[ok], pb[ok], model="6dof", options=ransac, min_inliers=options.min_shared
    )
    errors = known_pose_errors_px(b_from_a.R, b_from_a.t, xa[ok], xb[ok], camera_a.focal, camera_b.focal)
    return int(est.num_inliers), int(np.count_nonzero(errors < options.pose_threshold_px))


def nearest_first(centers: object, map_centers: object) -> np.ndarray:
    """Indices of ``centers`` ordered by the distance to their nearest map centre (stable).

    Args:
        centers: (K, 3) camera centres of the appended images, world frame they claim.
        map_centers: (M, 3) camera centres of the map images, M >= 1.

    Returns:
        (K,) int64 permutation, nearest first.
    """
    c = check_array("centers", centers, (None, 3))
    m = check_array("map_centers", map_centers, (None, 3))
    if len(m) == 0:
        raise InputError("map_centers: expected at least one map camera centre, got none")
    if len(c) == 0:
        return np.zeros(0, dtype=np.int64)
    d = np.min(np.linalg.norm(c[:, None, :] - m[None, :, :], axis=2), axis=1)
    return np.argsort(d, kind="stable").astype(np.int64)


def capped(features: Features, max_features: int) -> Features:
    """At most ``max_features`` of ``features``: an evenly spread subset in stored order."""
    n = len(features)
    if n <= max_features:
        return features
    keep = np.linspace(0, n - 1, max_features).round().astype(np.int64)
    return Features(features.keypoints[keep], features.descriptors[keep], features.scales[keep])


class _MapView:
    """What the check reads from the map: poses, cameras, features, and its retrieval index."""

    def __init__(self, db: MapDatabase) -> None:
        self.db = db
        self.images = db.posed_images()
        self.centers = np.array([im.cam_from_world.center for im in self.images])
        by_id = {image_id: row for row, image_id in enumerate(db.image_ids())}  # both in id order
        self.vocabulary: VladVocabulary | None = None
        self.index: GlobalIndex | None = None
        self.index_rows: list[int] = []
        blob = db.get_blob(VOCABULARY_BLOB)
        gids, descs = db.get_global_descriptors()
        if blob is not None and len(gids) and all(int(i) in by_id for i in gids):
            self.vocabulary = VladVocabulary.from_bytes(blob)
            self.index = GlobalIndex(descs, basis=db.global_basis())
            self.index_rows = [by_id[int(i)] for i in gids]
        self._features: dict[int, Features] = {}

    def features(self, row: int, max_features: int) -> Features:
        if row not in self._features:
            self._features[row] = capped(self.db.get_features(self.images[row].name), max_features)
        return self._features[row]

    def candidates(self, image: PosedImage, feats: Features, options: FrameCheckOptions) -> list[int]:
        """Map rows to match ``image`` with: retrieved first, then the nearest by centre."""
        rows: list[int] = []
        if self.index is not None and self.vocabulary is not None and options.retrieved:
            found, _ = self.index.search(
                vlad_descriptor(self.vocabulary, feats.descriptors), options.retrieved
            )
            rows += [self.index_rows[int(i)] for i in found]
        d = np.linalg.norm(self.centers - image.cam_from_world.center, axis=1)
        rows += [
            int(i) for i in np.argsort(d, kind="stable")[: options.nearest + len(rows)] if int(i) not in rows
        ]
        return rows[: options.retrieved + options.nearest]


def check_appended_frames(
    db: MapDatabase,
    images: Sequence[PosedImage],
    extract: Extract,
    options: FrameCheckOptions = DEFAULT_FRAME_CHECK,
    mapper: Mapper = map,
) -> FrameCheck:
    """Whether ``images`` (to be appended) share the world frame of the map ``db`` (module doc).

    Args:
        db: the open map, with at least one image.
        images: the images a build would add (not those already in the map).
        extract: the local features of an appended image (the map's feature settings), or the
            reason it cannot be read (a string: that image is not checked).
        options: :class:`FrameCheckOptions`.
        mapper: runs ``extract`` on the (at most ``max_images``) images to check, in order, like
            the builtin ``map`` (the default), e.g. a thread pool's ``map``; all of them are
            extracted, also when the check stops early.

    Returns:
        :class:`FrameCheck`; ``related`` is True when no image could be checked (none given, or
        none readable).

    Raises:
        InputError: the map has no images.
    """
    start = time.perf_counter()
    out = FrameCheck(options=options)
    if not images:
        return out
    view = _MapView(db)
    if not view.images:
        raise InputError(f"{db.path}: the map has no images to check appended images against")
    centers = np.array([im.cam_from_world.center for im in images])
    chosen = [images[int(k)] for k in nearest_first(centers, view.centers)[: options.max_images]]
    extracted = list(
        mapper(extract, chosen)
    )  # all of them (in parallel with a pool's map): none left running
    for image, feats in zip(chosen, extracted):
        if isinstance(feats, str):
            continue
        feats = capped(feats, options.max_features)
        out.checked.append(image.name)
        for row in view.candidates(image, feats, options):
            ref = view.images[row]
            ref_feats = view.features(row, options.max_features)
            m = match_features(feats, ref_feats)
            ref_from_image = ref.cam_from_world @ image.cam_from_world.inverse()
            shared, agreeing = pair_support(
                image.camera,
                ref.camera,
                ref_from_image,
                feats.keypoints[m[:, 0]],
                ref_feats.keypoints[m[:, 1]],
                options,
            )
            out.pairs.append(
                PairEvidence(
                    image.name, ref.name, len(m), shared, agreeing, pair_verdict(shared, agreeing, options)
                )
            )
        if out.count("agrees") >= options.enough_agreeing and frames_related([p.verdict for p in out.pairs]):
            break
    out.related = frames_related([p.verdict for p in out.pairs]) if out.checked else True
    out.seconds = time.perf_counter() - start
    logger.info(
        "%s: world frame check of %d appended images in %.1f s: %s",
        db.path,
        len(images),
        out.seconds,
        out.summary(),
    )
    return out
