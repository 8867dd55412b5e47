"""How well a map's poses agree with its images: the map prior, measured from the map itself.

The estimator treats each map image's pose as uncertain (``RansacOptions.map_rotation_std_deg``,
``map_position_std_m``; :mod:`planarloc.robust.map_prior`). Those two numbers decide much of a
fix's reported uncertainty, so they are measured rather than assumed: for pairs of neighbouring
map images, the relative pose their matches give (5-point RANSAC and refinement,
:func:`planarloc.robust.relative_pose.estimate_relative_pose`) is compared with the relative pose
their stored poses claim (:func:`pair_discrepancy`).

If every image's rotation error is independent with std ``σ_r`` per axis, a pair's relative
rotation error has ``2σ_r²`` per axis and its angle ``θ`` satisfies ``θ² ~ 2σ_r² χ²₃``; the
position errors (std ``σ_p`` per axis) turn the relative translation's direction by an angle
``α`` with ``(α·b)² ~ 2σ_p² χ²₂`` across the baseline ``b``. Medians over the pairs give the two
stds (:func:`accuracy_from_discrepancies`): robust to a few wrong relative poses, and never below
what the estimation noise of the relative poses leaves (which they include: a map whose poses
agree with its images to keypoint noise gets priors at that noise level, a map whose poses do
not gets large ones).

:func:`measure_map_accuracy` runs this over at most ``max_pairs`` pairs of a map (each image with
its nearest images by centre); :func:`planarloc.map.builder.build_map` stores the result in the
map (:func:`store_accuracy`), ``planarloc map info`` prints it and the localizer uses it as its map
prior (:func:`load_accuracy`).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from planarloc.features.matching import match_features
from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import essential_from_relpose, sampson_error_sq
from planarloc.geometry.pose import Pose
from planarloc.geometry.so3 import so3_exp, so3_log
from planarloc.geometry.validation import check_array
from planarloc.map.store import MapDatabase
from planarloc.robust.options import RansacOptions
from planarloc.robust.relative_pose import RayPairs, direction_basis, estimate_relative_pose

logger = logging.getLogger(__name__)

ACCURACY_META = "pose_accuracy"
"""Meta key of the stored :class:`MapPoseAccuracy` (JSON)."""
CHI2_3_MEDIAN = 2.365974
"""Median of a χ² variable with 3 degrees of freedom (rotation angle of a 3-axis error)."""
CHI2_2_MEDIAN = 1.386294
"""Median of a χ² variable with 2 degrees of freedom (an error across a baseline)."""
MIN_PAIRS = 3
"""Fewer measured pairs than this is no measurement (the configured prior stays)."""
MIN_PAIR_INLIERS = 40
"""A pair's relative pose counts with at least this many inliers."""
MIN_ROTATION_STD_DEG = 0.002
"""Floor of the measured rotation std: below it, the measurement cannot tell."""
MIN_POSITION_STD_M = 0.0003
"""Floor of the measured position std (metres, or the map's units)."""
NOISE_SCALES = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
"""Candidate factors on the relative poses' linearised covariance (variance): rendered and real
keypoints are not the independent Gaussian noise it assumes (a perfectly posed rendered room gave
Mahalanobis discrepancies of 21 against χ²₅'s 4.4 at the median); estimated with the map stds."""
OUTLIER_SHARE = 0.1
"""Prior share of pairs whose measured relative pose is wrong (repeated structure, a plane)."""
OUTLIER_STD_RAD = 0.1
"""Spread of a wrong relative pose's discrepancy, per coordinate (radians, about 6°)."""


@dataclass(frozen=True)
class PairDiscrepancy:
    """A map image pair's relative pose from its matches against the one its poses claim.

    Attributes:
        delta: (5,) the claimed relative pose in the measured one's tangent space: the rotation
            vector ``ω`` with ``R_claimed = Exp(ω) R_measured`` (radians, 3) and the claimed
            translation direction's offset across the measured one (radians, 2, in the basis
            :func:`planarloc.robust.relative_pose.direction_basis` of the measured direction).
        cov: (5, 5) covariance of the measured relative pose in the same coordinates, from its
            keypoint noise (``σ̂² (JᵀJ)⁻¹`` of the Sampson residuals of its inliers).
        baseline_m: the claimed distance between the two centres.
        inliers: inliers of the measured relative pose.
        residual_px: RMS Sampson error of the inliers under the measured pose: the keypoint
            noise (the Sampson error of a match with isotropic noise σ in both images has std σ).
    """

    delta: np.ndarray
    cov: np.ndarray
    baseline_m: float
    inliers: int
    residual_px: float

    @property
    def rotation_deg(self) -> float:
        """Angle between the claimed and measured relative rotations."""
        return math.degrees(float(np.linalg.norm(self.delta[:3])))


@dataclass(frozen=True)
class MapPoseAccuracy:
    """The map prior measured from a map's images.

    Attributes:
        rotation_std_deg: std of one map image's rotation error, per axis (degrees).
        position_std_m: std of one map image's centre error, per axis (map units).
        pairs: image pairs that measured a relative pose.
        keypoint_std_px: the map images' keypoint noise (median over the pairs of their RMS
            Sampson error): what points triangulated from them inherit.
    """

    rotation_std_deg: float
    position_std_m: float
    pairs: int
    keypoint_std_px: float = float("nan")

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> MapPoseAccuracy:
        return cls(**json.loads(text))

    def summary(self) -> str:
        return (
            f"map poses agree with their images to {self.rotation_std_deg:.2g}° / "
            f"{self.position_std_m:.2g} m "
            f"per image, keypoint noise {self.keypoint_std_px:.2g} px (measured on {self.pairs} image pairs)"
        )


def _signed_sampson_px(R: np.ndarray, t: np.ndarray, rays: RayPairs) -> np.ndarray:
    """(N,) signed Sampson errors (pixels) of ``x_bᵀ [t]x R x_a = 0``."""
    xa, xb, fa, fb = rays
    E = essential_from_relpose(R, t)
    sign = np.sign(np.einsum("ij,ij->i", xb, xa @ E.T))
    return sign * np.sqrt(sampson_error_sq(E, xa, xb, fa, fb))


def _refined_with_covariance(
    R: np.ndarray, t: np.ndarray, rays: RayPairs, iterations: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A relative pose ``(R, t)`` (unit ``t``) refined by Gauss-Newton on the Sampson residuals
    (pixels) of its N inliers ``rays``, and its (5, 5) covariance ``σ̂² (JᵀJ)⁻¹``
    (rotation increment, direction offset; central-difference Jacobian) and ``σ̂`` (pixels).

    The RANSAC's own refinement stops at a tolerance, and its robust loss weighs the inliers; the
    covariance is of the least-squares optimum it linearises at, so the pose is taken there.
    """

    def residuals(R0: np.ndarray, t0: np.ndarray, B: np.ndarray, p: np.ndarray) -> np.ndarray:
        t_p = t0 + B @ p[3:]
        return _signed_sampson_px(so3_exp(p[:3])[0] @ R0, t_p / np.linalg.norm(t_p), rays)

    h = 1e-6
    for k in range(iterations + 1):
        B = direction_basis(t)
        r0 = residuals(R, t, B, np.zeros(5))
        J = np.empty((len(r0), 5))
        for a in range(5):
            step = np.zeros(5)
            step[a] = h
            J[:, a] = (residuals(R, t, B, step) - residuals(R, t, B, -step)) / (2 * h)
        JtJ = J.T @ J
        if k == iterations:
            break
        delta = -np.linalg.lstsq(JtJ, J.T @ r0, rcond=None)[0]
        R = so3_exp(delta[:3])[0] @ R
        t = t + B @ delta[3:]
        t = t / np.linalg.norm(t)
    sigma2 = float(r0 @ r0) / max(len(r0) - 5, 1)
    return R, t, sigma2 * np.linalg.pinv(JtJ), math.sqrt(sigma2)


def pair_discrepancy(
    camera_a: Camera,
    camera_b: Camera,
    b_from_a: Pose,
    points_a: object,
    points_b: object,
    threshold_px: float = 2.0,
    seed: int = 0,
) -> PairDiscrepancy | None:
    """How far the relative pose of N pixel matches is from the claimed ``b_from_a``.

    Args:
        camera_a, camera_b: intrinsics of the two images.
        b_from_a: the relative pose the images' stored poses claim,
            ``cam_from_world_b · cam_from_world_a.inverse()``.
        points_a, points_b: (N, 2) matching pixels.
        threshold_px: Sampson inlier threshold of the relative-pose RANSAC.
        seed: its seed.

    Returns:
        :class:`PairDiscrepancy`, or None when the matches give no relative pose with at least
        :data:`MIN_PAIR_INLIERS` inliers, or the claimed poses have no baseline.
    """
    pa = check_array("points_a", points_a, (None, 2))
    pb = check_array("points_b", points_b, (len(pa), 2))
    baseline = float(np.linalg.norm(b_from_a.t))
    if len(pa) < MIN_PAIR_INLIERS or not baseline > 0:
        return None
    options = RansacOptions(threshold_px=threshold_px, min_iterations=50, max_iterations=300, seed=seed)
    est = estimate_relative_pose(
        camera_a, camera_b, pa, pb, model="6dof", options=options, min_inliers=MIN_PAIR_INLIERS
    )
    if not est.success or est.pose is None:
        return None
    R, t = est.pose.R, est.pose.t / np.linalg.norm(est.pose.t)
    xa = np.column_stack([camera_a.cam_from_img(pa[est.inliers]), np.ones(est.num_inliers)])
    xb = np.column_stack([camera_b.cam_from_img(pb[est.inliers]), np.ones(est.num_inliers)])
    rays = RayPairs(xa, xb, np.asarray(camera_a.focal, float), np.asarray(camera_b.focal, float))
    R, t, cov, sigma = _refined_with_covariance(R, t, rays)
    delta = np.concatenate([so3_log(b_from_a.R @ R.T)[0], direction_basis(t).T @ (b_from_a.t / baseline)])
    return PairDiscrepancy(delta, cov, baseline, int(est.num_inliers), sigma)


def _log_likelihood(
    pairs: Sequence[PairDiscrepancy],
    rotation_var: np.ndarray,
    position_var: np.ndarray,
    noise_scale: np.ndarray,
) -> np.ndarray:
    """Log-likelihood of the pairs' discrepancies for each pair of per-image variances (rotation
    rad², position m²; arrays of one shape).

    A pair's discrepancy is ``δ ~ N(0, C + M)`` with the map's share
    ``M = diag(2σ_r² I₃, (2σ_p² / b² + σ_r²) I₂)``, or, with probability :data:`OUTLIER_SHARE`,
    a wrong relative pose ``δ ~ N(0, C + σ_o² I)`` (σ_o = :data:`OUTLIER_STD_RAD`): a mixture,
    so that a few wrong pairs do not raise the stds, while a map whose every pair disagrees is
    not mistaken for one whose pairs are all wrong.
    """

    def log_normal(delta: np.ndarray, S: np.ndarray) -> np.ndarray:
        sign, logdet = np.linalg.slogdet(S)
        z = np.einsum(
            "...i,...i->...",
            delta,
            np.linalg.solve(S, np.broadcast_to(delta, S.shape[:-1])[..., None])[..., 0],
        )
        return np.where(sign > 0, -0.5 * (z + logdet + 5 * math.log(2 * math.pi)), -np.inf)

    total = np.zeros(rotation_var.shape)
    for p in pairs:
        S = p.cov * noise_scale[..., None, None]
        rot = 2.0 * rotation_var
        across = 2.0 * position_var / p.baseline_m**2 + rotation_var
        for k in range(3):
            S[..., k, k] += rot
        for k in (3, 4):
            S[..., k, k] += across
        inlier = math.log(1.0 - OUTLIER_SHARE) + log_normal(p.delta, S)
        outlier = math.log(OUTLIER_SHARE) + log_normal(p.delta, S + OUTLIER_STD_RAD**2 * np.eye(5))
        total += np.logaddexp(inlier, outlier)
    return total


def accuracy_from_discrepancies(pairs: Sequence[PairDiscrepancy]) -> MapPoseAccuracy | None:
    """Per-image rotation and position stds from pair discrepancies: the maximum of
    :func:`_log_likelihood` on a grid (σ_r from 0.001° to 3°, σ_p from 0.1 mm to 3 m, and 0),
    floored at :data:`MIN_ROTATION_STD_DEG` and :data:`MIN_POSITION_STD_M`; None with fewer
    than :data:`MIN_PAIRS` pairs. Pairs whose estimation noise alone explains their discrepancy
    leave both stds at the floor: the map agrees with its images to keypoint noise."""
    pairs = [p for p in pairs if np.isfinite(p.delta).all() and np.isfinite(p.cov).all()]
    if len(pairs) < MIN_PAIRS:
        return None
    rot = np.concatenate([[0.0], np.radians(np.geomspace(1e-3, 3.0, 36))])
    pos = np.concatenate([[0.0], np.geomspace(1e-4, 3.0, 46)])
    R2, P2, K = np.meshgrid(rot**2, pos**2, NOISE_SCALES, indexing="ij")
    ll = _log_likelihood(pairs, R2, P2, K)
    i, j, _ = np.unravel_index(int(np.argmax(ll)), ll.shape)
    return MapPoseAccuracy(
        max(math.degrees(float(rot[i])), MIN_ROTATION_STD_DEG),
        max(float(pos[j]), MIN_POSITION_STD_M),
        len(pairs),
        float(np.median([p.residual_px for p in pairs])),
    )


def neighbour_pairs(centers: object, neighbours: int = 2, max_pairs: int = 60) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of each image with its ``neighbours`` nearest by centre
    (distinct centres only), at most ``max_pairs`` spread evenly over the list.

    Args:
        centers: (N, 3) camera centres.
    """
    c = check_array("centers", centers, (None, 3))
    if len(c) < 2:
        return []
    d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
    d[np.arange(len(c)), np.arange(len(c))] = np.inf
    d[d <= 0] = np.inf  # the same centre: no baseline to compare
    found: set[tuple[int, int]] = set()
    for i in range(len(c)):
        for j in np.argsort(d[i], kind="stable")[:neighbours]:
            if np.isfinite(d[i, j]):
                found.add((min(i, int(j)), max(i, int(j))))
    pairs = sorted(found)
    if len(pairs) > max_pairs:
        keep = np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int)
        pairs = [pairs[k] for k in np.unique(keep)]
    return pairs


Progress = Callable[[str, int, int], None]


def measure_map_accuracy(
    db: MapDatabase, max_pairs: int = 60, threshold_px: float = 2.0, progress: Progress | None = None
) -> MapPoseAccuracy | None:
    """:class:`MapPoseAccuracy` of the map ``db`` over at most ``max_pairs`` neighbour pairs
    (:func:`neighbour_pairs`); None when fewer than :data:`MIN_PAIRS` pairs measure a relative
    pose (too few images, or images that share too little)."""
    images = db.posed_images()
    pairs = neighbour_pairs(
        np.array([im.cam_from_world.center for im in images]).reshape(-1, 3), max_pairs=max_pairs
    )
    features: dict[int, object] = {}

    def feats(k: int):
        if k not in features:
            features[k] = db.get_features(images[k].name)
        return features[k]

    found: list[PairDiscrepancy] = []
    for n, (i, j) in enumerate(pairs):
        a, b = images[i], images[j]
        fa, fb = feats(i), feats(j)
        m = match_features(fa, fb)
        if len(m) >= MIN_PAIR_INLIERS:
            found_pair = pair_discrepancy(
                a.camera,
                b.camera,
                b.cam_from_world @ a.cam_from_world.inverse(),
                fa.keypoints[m[:, 0]],
                fb.keypoints[m[:, 1]],
                threshold_px,
            )
            if found_pair is not None:
                found.append(found_pair)
        if progress:
            progress("measure map poses", n + 1, len(pairs))
    accuracy = accuracy_from_discrepancies(found)
    logger.info(
        "%s: %s",
        db.path,
        accuracy.summary()
        if accuracy
        else f"map pose accuracy not measured ({len(found)} of {len(pairs)} pairs gave a relative pose)",
    )
    return accuracy


def store_accuracy(db: MapDatabase, accuracy: MapPoseAccuracy | None) -> None:
    """Store (or, for None, clear) the map's measured pose accuracy."""
    db.set_meta(ACCURACY_META, "" if accuracy is None else accuracy.to_json())


def load_accuracy(db: MapDatabase) -> MapPoseAccuracy | None:
    """The stored measurement; None for a map without one (built before it existed, or too
    small to measure)."""
    text = db.get_meta(ACCURACY_META)
    if not text:
        return None
    try:
        return MapPoseAccuracy.from_json(text)
    except (TypeError, ValueError, json.JSONDecodeError):
        logger.warning("%s: unreadable %s meta value ignored", db.path, ACCURACY_META)
        return None
