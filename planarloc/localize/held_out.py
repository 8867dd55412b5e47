"""The map's std calibration measured: each of a spread sample of map images held out in turn
and localized against the others (its own features, retrieval without it, the local structure
of the other map images), its error against its stored pose over the reported std
(:mod:`planarloc.map.std_calibration` holds the record and the factor it gives).

A held-out image's stored pose is the answer it is measured against, so it counts only where
that pose agrees with its images: its matches with the map images it retrieved, triangulated
under the stored poses, reproject as well as the map's poses do elsewhere
(:func:`stored_pose_disagreement_deg`). KITTI ``kitti_seq1``'s frame 4 (the road's first
second) reprojects 1.4-1.8 px off against every neighbour (0.17° of rotation against the map's
measured 0.08°); localized against the others it lands 32 cm from its stored pose at 2.8σ while
the 8 agreeing held-out images lie at 0.2-0.9σ, and that one doubtful answer kept the whole
map's std from shrinking (issue 30).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.pose import pose_errors
from planarloc.localize.local_structure import map_rotation_std_deg, view_points
from planarloc.localize.localizer import CARRYING_3D_INLIERS, Localizer
from planarloc.localize.localizer_config import LocalizerConfig
from planarloc.map.std_calibration import (
    MAX_HELD_OUT,
    MIN_SAMPLES,
    StdCalibration,
    load_std_calibration,
    scale_from_ratios,
    std_calibration_due,
    store_std_calibration,
    tail_ratios,
)
from planarloc.map.store import MapDatabase

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
BeforeLocalizing = Callable[[LocalizerConfig], None]
"""Called with the localizer's configuration once the calibration is sure to localize held-out
images, before the first (a front door compiles the kernels it needs on every core there)."""


def held_out_names(names: list[str], most: int = MAX_HELD_OUT) -> list[str]:
    """At most ``most`` of ``names``, spread evenly over the list (the map's order)."""
    if len(names) <= most:
        return list(names)
    return [names[int(i)] for i in np.linspace(0, len(names) - 1, most).round().astype(int)]


def stored_pose_disagreement_deg(
    loc: Localizer, name: str, features: Features, references: list[str]
) -> float:
    """Rotation error (degrees) that map image ``name``'s stored pose implies against the map
    images ``references``: every one of its keypoints matched into them and triangulated under
    the stored poses as the local structure does (:func:`~planarloc.localize.local_structure.view_points`,
    the localizer's matcher, threshold and pair cache), its median reprojection error turned into
    a rotation by :func:`~planarloc.localize.local_structure.map_rotation_std_deg`; 0 where it
    agrees to keypoint noise or nothing could be measured."""
    views = [loc.map_view(n, loc.db.get_features(n)) for n in references]
    own = loc.map_view(name, features)
    points = view_points(
        [own, *views],
        [np.arange(len(features)), *(np.zeros(0, dtype=np.int64) for _ in views)],
        loc.pair_cache,
        ratio=loc.config.ratio,
        max_error_px=loc.config.ransac.threshold_px,
        keypoint_std_px=loc.keypoint_std_px,
    )
    return map_rotation_std_deg(points[0].pose_residual_px, float(np.mean(own.camera.focal)))


DOUBTFUL_POSE = "doubtful stored pose"
"""What :func:`held_out_measurement` returns for a map image whose stored pose disagrees with its images."""


def held_out_error(loc: Localizer, name: str) -> tuple[float, float] | None:
    """``(error_m, std_m)`` of :func:`held_out_measurement`; None where it has none."""
    measured = held_out_measurement(loc, name)
    return None if measured is None or isinstance(measured, str) else measured


def held_out_measurement(loc: Localizer, name: str) -> tuple[float, float] | str | None:
    """``(error_m, std_m)`` of map image ``name`` localized against the other map images (its own
    features, retrieval without it, the localizer's configuration): its position error against
    its stored pose and the reported std; None when it fails or is not in the calibrated regime:
    fewer than ``CARRYING_3D_INLIERS`` 2D-3D inliers (judged under the configured prior), or a map
    prior raised for this query because its retrieved map images disagree with their poses; the
    factor touches neither. :data:`DOUBTFUL_POSE` when its own stored pose disagrees with its
    images by more than the map's rotation prior (:func:`stored_pose_disagreement_deg`): no
    answer to measure against."""
    posed = next(p for p in loc.map_images if p.name == name)
    features = loc.db.get_features(name)
    refs = [r for r in loc.retrieve(features, loc.config.top_n + 1) if r != name][: loc.config.top_n]
    if (
        loc.ransac_options.map_prior_measured
        and stored_pose_disagreement_deg(loc, name, features, refs) > loc.ransac_options.map_rotation_std_deg
    ):
        return DOUBTFUL_POSE
    est = loc.localize_features(features, posed.camera, refs)
    if not est.success or est.pose is None or est.num_inliers_3d < CARRYING_3D_INLIERS:
        return None
    if est.map_prior is not None and est.map_prior[0] > loc.ransac_options.map_rotation_std_deg:
        return None  # the retrieved map images disagree with their poses: a raised prior, no factor
    std = est.position_std_m
    if std is None or not std > 0:
        return None
    return pose_errors(est.pose, posed.cam_from_world)[0], std


def held_out_ratio(loc: Localizer, name: str) -> float | None:
    """Error / std of :func:`held_out_error` (None where it is None)."""
    measured = held_out_error(loc, name)
    return None if measured is None else measured[0] / measured[1]


def calibrate_std(
    loc: Localizer, progress: Progress | None = None, before_localizing: BeforeLocalizing | None = None
) -> StdCalibration | None:
    """:class:`StdCalibration` of the map behind ``loc`` over at most :data:`MAX_HELD_OUT`
    held-out map images; None when the map has no measured pose accuracy (the factor applies
    only under the measured prior) or fewer than :data:`MIN_SAMPLES` held-out images count.
    ``before_localizing``: see :data:`BeforeLocalizing`."""
    if loc.pose_accuracy is None or loc.config.map_prior != "measured" or len(loc.map_images) < 3:
        return None
    if before_localizing is not None:
        before_localizing(loc.config)
    uncalibrated = loc.with_config(loc.config)
    uncalibrated.std_calibration = None  # the model's own std
    names = held_out_names([p.name for p in loc.map_images])
    measured, doubtful = [], []
    for n, name in enumerate(names):
        m = held_out_measurement(uncalibrated, name)
        if m == DOUBTFUL_POSE:
            doubtful.append(name)
        elif isinstance(m, tuple):
            measured.append(m)
        if progress:
            progress("calibrate the std", n + 1, len(names))
    if doubtful:
        logger.info(
            "%s: held-out map images whose stored pose disagrees with their images (not counted): %s",
            loc.db.path,
            ", ".join(doubtful),
        )
    if len(measured) < MIN_SAMPLES:
        logger.info(
            "%s: std not calibrated (%d of %d held-out images counted)",
            loc.db.path,
            len(measured),
            len(names),
        )
        return None
    errors, stds = np.array(measured).T
    ratios = errors / stds
    scale = scale_from_ratios(ratios, tail_ratios(errors, stds))
    out = StdCalibration(
        scale, len(ratios), len(names), float(np.median(ratios)), float(ratios.max()), tuple(doubtful)
    )
    logger.info("%s: %s", loc.db.path, out.summary())
    return out


def calibrate_map_std(
    path: str | Path, progress: Progress | None = None, before_localizing: BeforeLocalizing | None = None
) -> StdCalibration | None:
    """Measure the std calibration of the map file ``path`` with the default localizer and
    store it in the map (cleared when it cannot be measured)."""
    with MapDatabase.open(path, mode="a") as db:
        calibration = calibrate_std(Localizer(db), progress, before_localizing)
        store_std_calibration(db, calibration)
    return calibration


def calibrate_map_std_when_due(
    path: str | Path, progress: Progress | None = None, before_localizing: BeforeLocalizing | None = None
) -> StdCalibration | None:
    """The std calibration of the map file ``path``, measured and stored (:func:`calibrate_map_std`)
    when a build changed the map since, or never measured it; a read-only map keeps what it
    has (None when it has nothing). Returns the map's calibration."""
    path = Path(path)
    with MapDatabase.open(path) as db:
        due = std_calibration_due(db)
        stored = load_std_calibration(db)
    if not due:
        return stored
    if not (os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)):
        logger.info("%s: read-only map, its std calibration is not measured", path)
        return stored
    return calibrate_map_std(path, progress, before_localizing)
