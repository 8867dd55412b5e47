"""The hloc-style peer: a COLMAP triangulation of the posed map images, then 2D-3D matching and PnP.

What a robotics user would run instead of planarloc (hloc's ``triangulation.py`` and
``localize_sfm.py`` recipe, with pycolmap 4.x), on the features and the retrieval it is given:

1. **Map** (:meth:`ColmapPeer.build`, once per map): a ``pycolmap.Reconstruction`` holding every
   map image at its known ``cam_from_world``; a COLMAP database with their keypoints and, for
   each map image and its ``neighbours`` nearest map images by camera centre (every pair when the
   map has at most ``exhaustive_up_to`` images), the mutual-nearest-neighbour matches that pass
   Lowe's ratio test (0.8) and hloc's known-pose geometric verification (distance to the
   epipolar line of the known relative pose below ``verify_px`` = 4 px in both images, hloc's
   ``geometric_verification(max_error=4.0)``); then ``pycolmap.triangulate_points`` (COLMAP's
   ``point_triangulator``: poses held fixed, its default options, bundle adjustment of the
   points only). Each map keypoint then has a triangulated ``point3D_id`` or none.
2. **Query** (:meth:`ColmapPeer.localize`): the query's keypoints are matched to each given
   reference (mutual NN + ratio 0.8); every match whose reference keypoint has a 3D point gives
   a 2D-3D correspondence (one per distinct (query keypoint, 3D point), as hloc's
   ``pose_from_cluster``); ``pycolmap.estimate_and_refine_absolute_pose`` with hloc's
   ``max_error`` of 12 px, seeded. The query fails when pycolmap returns None or fewer than
   ``min_inliers`` inliers.

Conventions: poses are ``cam_from_world`` in both libraries (``x_cam = R x_world + t``).
pycolmap's ``Rotation3d`` quaternion is (x, y, z, w), planarloc's ``quat_wxyz`` is (w, x, y, z):
:func:`rigid3d_from_pose` / :func:`pose_from_rigid3d` convert, and ``calibration.py
--self-check`` checks the round trip and a noise-free end-to-end run to 1e-9. Keypoints are
given to COLMAP as they are, without hloc's ``+ 0.5``: hloc adds it because its keypoints use
OpenCV's pixel centres and its cameras COLMAP's, whereas here the cameras' principal points are
in the same (OpenCV) convention as the keypoints (planarloc's ``Camera``).

Not part of the package: benchmarks sit on top of it and may import anything.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.map.posed_image import PosedImage

try:
    import pycolmap
except ImportError:  # the peer is optional: `pip install -e ".[bench]"`
    pycolmap = None

logger = logging.getLogger(__name__)

RATIO = 0.8
"""Lowe's ratio (hloc's ``NN-ratio`` matcher, with its mutual check)."""
VERIFY_PX = 4.0
"""Known-pose geometric verification of map pairs: max distance to the epipolar line (hloc: 4 px)."""
PNP_PX = 12.0
"""RANSAC threshold of the absolute pose (hloc ``localize_sfm``'s ``ransac_thresh``)."""
NEIGHBOURS = 5
"""Map pairs for the triangulation: each map image with this many nearest map images by centre."""
EXHAUSTIVE_UP_TO = 12
"""Maps with at most this many images match every pair."""
MIN_INLIERS = 12
"""A pose with fewer PnP inliers is a failure (hloc has no threshold; COLMAP's mapper uses 30)."""
SEED = 0


def have_pycolmap() -> bool:
    return pycolmap is not None


def pycolmap_version() -> str | None:
    return None if pycolmap is None else str(pycolmap.__version__)


def _require() -> None:
    if pycolmap is None:
        raise RuntimeError(
            "the COLMAP peer needs pycolmap: pip install -e '.[bench]' (or pip install pycolmap)"
        )


# ---- conversions ------------------------------------------------------------------------------------
def colmap_camera(camera: Camera, camera_id: int = 1) -> pycolmap.Camera:
    """A planarloc Camera as a pycolmap Camera (same COLMAP model names and parameter order)."""
    _require()
    return pycolmap.Camera(
        model=camera.model.value,
        width=int(camera.width),
        height=int(camera.height),
        params=np.asarray(camera.params, dtype=np.float64),
        camera_id=camera_id,
    )


def rigid3d_from_pose(pose: Pose) -> pycolmap.Rigid3d:
    """A planarloc Pose (``b_from_a``) as a pycolmap Rigid3d (same ``x_b = R x_a + t``); the
    quaternion goes from planarloc's (w, x, y, z) to pycolmap's (x, y, z, w)."""
    _require()
    q_wxyz = np.asarray(pose.quat_wxyz, dtype=np.float64)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(q_wxyz[[1, 2, 3, 0]]), np.asarray(pose.t, dtype=np.float64))


def pose_from_rigid3d(rigid: pycolmap.Rigid3d) -> Pose:
    """Inverse of :func:`rigid3d_from_pose`."""
    q_xyzw = np.asarray(rigid.rotation.quat, dtype=np.float64)
    return Pose.from_quat_wxyz(q_xyzw[[3, 0, 1, 2]], np.asarray(rigid.translation, dtype=np.float64))


# ---- matching and verification ------------------------------------------------------------------------
def mutual_ratio_matches(d1: np.ndarray, d2: np.ndarray, ratio: float = RATIO) -> np.ndarray:
    """(K, 2) int indices (into d1, into d2) of the mutual nearest neighbours that pass Lowe's
    ratio test in the d1 -> d2 direction (hloc's ``nearest_neighbor`` matcher, ``mutual_check``).
    Descriptors are L2-normalised rows, so squared distances are ``2 - 2 sim``."""
    if len(d1) < 1 or len(d2) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    d1, d2 = np.asarray(d1, dtype=np.float32), np.asarray(d2, dtype=np.float32)
    sim = d1 @ d2.T
    rows = np.arange(len(d1))
    nn = np.argmax(sim, axis=1)
    s1 = sim[rows, nn].copy()
    sim[rows, nn] = -np.inf
    s2 = sim.max(axis=1)  # the second nearest neighbour
    dist1, dist2 = np.maximum(2.0 - 2.0 * s1, 0.0), np.maximum(2.0 - 2.0 * s2, 0.0)
    ok = dist1 <= ratio * ratio * dist2
    ok &= np.argmax(d2 @ d1.T, axis=1)[nn] == rows  # mutual (a second product: faster than a column argmax)
    return np.stack([rows[ok], nn[ok]], axis=1).astype(np.int64)


def epipolar_errors_px(
    b_from_a: Pose, cam_a: Camera, cam_b: Camera, kp_a: np.ndarray, kp_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distances (pixels, via each camera's mean focal length) of matched keypoints to the epipolar
    lines of the known relative pose, in image a and in image b (hloc ``compute_epipolar_errors``)."""
    xa = cam_a.bearings_from_img(np.asarray(kp_a, dtype=np.float64))
    xb = cam_b.bearings_from_img(np.asarray(kp_b, dtype=np.float64))
    xa = xa / xa[:, 2:3]
    xb = xb / xb[:, 2:3]
    t = np.asarray(b_from_a.t, dtype=np.float64)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ np.asarray(b_from_a.R)
    line_b = xa @ E.T  # lines in image b
    line_a = xb @ E  # lines in image a
    dist = np.abs(np.sum(xb * line_b, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        err_a = dist / np.linalg.norm(line_a[:, :2], axis=1) * float(np.mean(cam_a.focal))
        err_b = dist / np.linalg.norm(line_b[:, :2], axis=1) * float(np.mean(cam_b.focal))
    return np.nan_to_num(err_a, nan=np.inf), np.nan_to_num(err_b, nan=np.inf)


def map_pairs(
    images: Sequence[PosedImage], neighbours: int = NEIGHBOURS, exhaustive_up_to: int = EXHAUSTIVE_UP_TO
) -> list[tuple[int, int]]:
    """Index pairs (i < j) of map images to match: all pairs of a small map, else each image with
    its ``neighbours`` nearest by camera centre."""
    n = len(images)
    if n <= exhaustive_up_to:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    centres = np.array([im.cam_from_world.center for im in images])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    np.fill_diagonal(d, np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(d[i], kind="stable")[:neighbours]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


@contextmanager
def _quiet_colmap(verbose: bool):
    """COLMAP logs every image it reads for colours (none here): only errors unless ``verbose``."""
    before = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


# ---- the peer ------------------------------------------------------------------------------------------
@dataclass
class PeerEstimate:
    """The peer's outcome on one query: ``pose`` (``cam_from_world``) is None on failure."""

    pose: Pose | None
    success: bool
    status: str
    num_inliers: int
    num_correspondences: int
    seconds: float
    info: dict = field(default_factory=dict)
    position_std_m: float = float("nan")
    """What the 2D-3D data alone say about the position (:func:`absolute_pose`)."""


@dataclass
class MapModel:
    """A triangulated map: ``xyz`` (P, 3) world points; ``point_index`` per map image name, the
    row of ``xyz`` each of its keypoints observes (-1: none)."""

    xyz: np.ndarray
    point_index: dict[str, np.ndarray]
    stats: dict


class ColmapPeer:
    """hloc's recipe on posed map images (module docstring).

    Args:
        map_images: the map's posed images.
        features: the local features of a map image (e.g. ``MapDatabase.get_features`` by name,
            or an extractor); called once per map image.
        workdir: where the COLMAP database and model go (default: a temporary folder).
        neighbours, exhaustive_up_to: the map pairs (:func:`map_pairs`).
        min_inliers: fewer PnP inliers is a failure.
        verbose: let COLMAP log.

    Example:
        >>> peer = ColmapPeer(map_images, lambda im: db.get_features(im.name)).build()   # doctest: +SKIP
        >>> est = peer.localize(query_features, query_camera, ["image_l/000004.png", ...])  # doctest: +SKIP
    """

    def __init__(
        self,
        map_images: Sequence[PosedImage],
        features: Callable[[PosedImage], Features],
        workdir: Path | None = None,
        *,
        neighbours: int = NEIGHBOURS,
        exhaustive_up_to: int = EXHAUSTIVE_UP_TO,
        min_inliers: int = MIN_INLIERS,
        verbose: bool = False,
    ) -> None:
        _require()
        self.map_images = list(map_images)
        self._features_of = features
        self.workdir = Path(workdir) if workdir is not None else None
        self.neighbours, self.exhaustive_up_to = neighbours, exhaustive_up_to
        self.min_inliers = int(min_inliers)
        self.verbose = verbose
        self.features: dict[str, Features] = {}
        self.model: MapModel | None = None
        self.build_seconds = 0.0

    # ---- map ------------------------------------------------------------------------------------
    def build(self) -> ColmapPeer:
        """Match, verify and triangulate the map (module docstring, step 1); returns self."""
        t0 = time.perf_counter()
        if self.workdir is None:
            with tempfile.TemporaryDirectory(prefix="colmap-peer-") as tmp:
                self.model = self._triangulate(Path(tmp))
        else:
            self.workdir.mkdir(parents=True, exist_ok=True)
            self.model = self._triangulate(self.workdir)
        self.build_seconds = time.perf_counter() - t0
        self.model.stats["seconds"] = self.build_seconds
        return self

    def _triangulate(self, work: Path) -> MapModel:
        images = self.map_images
        t0 = time.perf_counter()
        for im in images:
            self.features[im.name] = self._features_of(im)
        t_features = time.perf_counter() - t0
        db_path = work / "database.db"
        db_path.unlink(missing_ok=True)
        (work / "images").mkdir(exist_ok=True)  # colours are not needed: an empty image folder
        (work / "model").mkdir(exist_ok=True)
        reference = pycolmap.Reconstruction()
        camera_ids: dict[Camera, int] = {}
        db = pycolmap.Database.open(str(db_path))
        try:
            for im in images:
                if im.camera not in camera_ids:
                    camera_ids[im.camera] = len(camera_ids) + 1
                    cam = colmap_camera(im.camera, camera_ids[im.camera])
                    reference.add_camera_with_trivial_rig(cam)
                    db.write_camera(cam, use_camera_id=True)
            for rig in reference.rigs.values():
                db.write_rig(rig, use_rig_id=True)
            for i, im in enumerate(images):
                image_id = i + 1
                kp = np.asarray(self.features[im.name].keypoints, dtype=np.float64).reshape(-1, 2)
                image = pycolmap.Image(
                    name=im.name, keypoints=kp, camera_id=camera_ids[im.camera], image_id=image_id
                )
                reference.add_image_with_trivial_frame(image, rigid3d_from_pose(im.cam_from_world))
                db.write_frame(reference.frame(image_id), use_frame_id=True)
                db_image = pycolmap.Image(name=im.name, camera_id=camera_ids[im.camera], image_id=image_id)
                db_image.frame_id = image_id
                db.write_image(db_image, use_image_id=True)
                db.write_keypoints(image_id, kp.astype(np.float32))
            pairs = map_pairs(images, self.neighbours, self.exhaustive_up_to)
            raw = verified = 0
            for i, j in pairs:
                a, b = images[i], images[j]
                fa, fb = self.features[a.name], self.features[b.name]
                m = mutual_ratio_matches(fa.descriptors, fb.descriptors)
                raw += len(m)
                b_from_a = b.cam_from_world @ a.cam_from_world.inverse()
                ea, eb = epipolar_errors_px(
                    b_from_a, a.camera, b.camera, fa.keypoints[m[:, 0]], fb.keypoints[m[:, 1]]
                )
                keep = m[(ea <= VERIFY_PX) & (eb <= VERIFY_PX)]
                verified += len(keep)
                db.write_matches(i + 1, j + 1, m.astype(np.uint32))
                geometry = pycolmap.TwoViewGeometry()
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                geometry.inlier_matches = keep.astype(np.uint32)
                db.write_two_view_geometry(i + 1, j + 1, geometry)
        finally:
            db.close()
        options = pycolmap.IncrementalPipelineOptions()
        options.triangulation.random_seed = SEED
        with _quiet_colmap(self.verbose):
            model = pycolmap.triangulate_points(
                reference, str(db_path), str(work / "images"), str(work / "model"), options=options
            )
        row = {pid: k for k, pid in enumerate(model.point3D_ids())}
        xyz = np.array([model.point3D(pid).xyz for pid in row], dtype=np.float64).reshape(-1, 3)
        point_index: dict[str, np.ndarray] = {}
        for image in model.images.values():
            point_index[image.name] = np.array(
                [row[p.point3D_id] if p.has_point3D() else -1 for p in image.points2D], dtype=np.int64
            )
        stats = {
            "map_images": len(images),
            "features_seconds": round(t_features, 2),
            "pairs": len(pairs),
            "raw_matches": raw,
            "verified_matches": verified,
            "points3D": model.num_points3D(),
            "mean_track_length": float(model.compute_mean_track_length()) if model.num_points3D() else 0.0,
            "mean_reprojection_error_px": float(model.compute_mean_reprojection_error())
            if model.num_points3D()
            else None,
        }
        # the model's poses are the given ones (held fixed): checked, since everything rests on it
        for image in model.images.values():
            truth = images[image.image_id - 1]
            if image.name != truth.name:
                raise RuntimeError(f"COLMAP renumbered the map images: {image.name} != {truth.name}")
            got = pose_from_rigid3d(image.cam_from_world())
            if not (
                np.allclose(got.R, truth.cam_from_world.R, atol=1e-9)
                and np.allclose(got.t, truth.cam_from_world.t, atol=1e-9)
            ):
                raise RuntimeError(f"COLMAP moved the pose of map image {image.name}")
        return MapModel(xyz, point_index, stats)

    # ---- query ----------------------------------------------------------------------------------
    def correspondences(self, features: Features, references: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) query keypoints and (N, 3) world points through the references' triangulated
        keypoints; one row per distinct (query keypoint, 3D point)."""
        if self.model is None:
            raise RuntimeError("ColmapPeer.build() first")
        pairs = []
        for name in references:
            index = self.model.point_index.get(name)
            if index is None:
                raise KeyError(f"reference not in the peer's map: {name}")
            m = mutual_ratio_matches(features.descriptors, self.features[name].descriptors)
            pid = index[m[:, 1]]
            pairs.append(np.stack([m[:, 0], pid], axis=1)[pid >= 0])
        qp = np.unique(np.concatenate(pairs, axis=0) if pairs else np.zeros((0, 2), np.int64), axis=0)
        return (
            np.asarray(features.keypoints, dtype=np.float64)[qp[:, 0]].reshape(-1, 2),
            self.model.xyz[qp[:, 1]].reshape(-1, 3),
        )

    def localize(self, features: Features, camera: Camera, references: Sequence[str]) -> PeerEstimate:
        """The query's ``cam_from_world`` from its features and retrieved map images (step 2)."""
        t0 = time.perf_counter()
        x2d, x3d = self.correspondences(features, references)
        return self.pose_from_correspondences(x2d, x3d, camera, t0)

    def pose_from_correspondences(
        self, x2d: np.ndarray, x3d: np.ndarray, camera: Camera, started: float | None = None
    ) -> PeerEstimate:
        t0 = time.perf_counter() if started is None else started
        n = len(x2d)
        if n < 4:
            return PeerEstimate(None, False, "too_few_2d3d", 0, n, time.perf_counter() - t0)
        ret = absolute_pose(x2d, x3d, camera)
        seconds = time.perf_counter() - t0
        if ret is None:
            return PeerEstimate(None, False, "pnp_failed", 0, n, seconds)
        info = {"reprojection_rms_px": ret.reprojection_rms_px}
        if ret.num_inliers < self.min_inliers:
            return PeerEstimate(
                None,
                False,
                "few_inliers",
                ret.num_inliers,
                n,
                seconds,
                info | {"pose_with_few_inliers": ret.pose},
                ret.position_std_m,
            )
        return PeerEstimate(ret.pose, True, "success", ret.num_inliers, n, seconds, info, ret.position_std_m)


@dataclass
class AbsolutePose:
    """pycolmap's absolute pose: ``cam_from_world``, its inliers, and the position standard
    deviation along the worst axis (metres; see :func:`absolute_pose`)."""

    pose: Pose
    num_inliers: int
    position_std_m: float
    reprojection_rms_px: float


def absolute_pose(
    x2d: np.ndarray, x3d: np.ndarray, camera: Camera, max_error_px: float = PNP_PX, seed: int = SEED
) -> AbsolutePose | None:
    """``pycolmap.estimate_and_refine_absolute_pose`` (LO-RANSAC P3P + refinement) with hloc's
    threshold, or None when pycolmap finds no pose.

    ``position_std_m`` is what the 2D-3D data alone say (the world points taken as exact): the
    refinement's 6x6 covariance (pycolmap: rotation then translation of ``cam_from_world``, the
    rotation perturbed on the left, ``R' = Exp(δ) R``, for 1 px of keypoint noise) mapped to the
    camera centre ``c = -Rᵀt`` (Jacobian ``[-Rᵀ[t]x, -Rᵀ]``), scaled by the inliers' RMS
    reprojection error per coordinate, square root of its largest eigenvalue. NaN when pycolmap
    gives no covariance.
    """
    _require()
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = float(max_error_px)
    options.ransac.random_seed = int(seed)
    x2d = np.ascontiguousarray(x2d, dtype=np.float64)
    x3d = np.ascontiguousarray(x3d, dtype=np.float64)
    ret = pycolmap.estimate_and_refine_absolute_pose(
        x2d, x3d, colmap_camera(camera), options, return_covariance=True
    )
    if ret is None:
        return None
    pose = pose_from_rigid3d(ret["cam_from_world"])
    inliers = np.asarray(ret["inlier_mask"], dtype=bool)
    Xc = x3d[inliers] @ pose.R.T + pose.t
    front = Xc[:, 2] > 0
    rms = float("nan")
    if front.sum() > 3:
        r = camera.img_from_cam(Xc[front]) - x2d[inliers][front]
        rms = float(np.sqrt(np.sum(r * r) / max(2 * int(front.sum()) - 6, 1)))
    std = float("nan")
    cov = ret.get("covariance")
    if cov is not None and np.isfinite(rms):
        t = pose.t
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        J = np.hstack([-pose.R.T @ tx, -pose.R.T])
        c_cov = J @ np.asarray(cov, dtype=np.float64) @ J.T * rms * rms
        std = float(np.sqrt(max(np.linalg.eigvalsh(c_cov).max(), 0.0)))
    return AbsolutePose(pose, int(ret["num_inliers"]), std, rms)


def split_peer(
    map_images: Sequence[PosedImage],
    features: Mapping[str, Features] | Callable[[PosedImage], Features],
    workdir: Path | None = None,
    **kwargs: object,
) -> ColmapPeer:
    """A built :class:`ColmapPeer` of one map split; ``features`` by map image name or a callable."""
    get = (lambda im: features[im.name]) if isinstance(features, Mapping) else features
    return ColmapPeer(map_images, get, workdir, **kwargs).build()  # type: ignore[arg-type]
