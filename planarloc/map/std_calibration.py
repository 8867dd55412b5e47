"""How the reported position std relates to real errors on a map: the record the map stores.

The std of a pose carried by 2D-3D constraints is a model (:mod:`planarloc.robust.covariance`):
pixel noise, the map's measured pose errors (:mod:`planarloc.map.pose_accuracy`) propagated
through the triangulated points, the points' own noise. Where the model's assumptions do not hold
(map pose disagreements that are not independent per image, calibration errors shared by every
image), it can be several times the error (Strecha ``entry_p10``: median error / std 0.29) or
short of it. The map can tell: a map image localized against the others has a known answer, its
stored pose (:mod:`planarloc.localize.held_out` measures it). Over a spread sample of held-out
images the ratios ``error / std`` give one factor for the map (:func:`scale_from_ratios`): the
std shrunk until the median ratio reaches :data:`TARGET_MEDIAN_RATIO` while the largest stays at
most :data:`MAX_RATIO`. Both biases of the measurement err on the side of a larger std: the
stored pose is not the truth (its error is part of the measured one), and a held-out image is
further from the other map images than a query among them. (A map whose poses are worse than
its prior says is the map prior's to catch, :mod:`planarloc.map.pose_accuracy`.)

The :class:`~planarloc.localize.localizer.Localizer` applies the stored factor
(``RansacOptions.std_scale``) to poses judged in the regime it was measured in: a measured map
prior and enough 2D-3D inliers to carry the pose.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from planarloc.map.store import MapDatabase

logger = logging.getLogger(__name__)


STD_CALIBRATION_META = "std_calibration"
"""Meta key of the stored :class:`StdCalibration` (JSON); ``""`` once measured without a result,
:data:`STALE` after a build changed the map, absent before the first measurement."""
STALE = "stale"
"""The meta value of a calibration a build has made out of date (the map changed since)."""
TARGET_MEDIAN_RATIO = 0.85
"""Median held-out error / std the factor aims at, about a calibrated Gaussian's (0.67 along one
dominant axis, 1.5 for three equal ones). Held-out images are not queries: some maps' queries land
lower (the rendered gallery: held-out 0.48, queries 0.31 without a factor), others higher (the
office worlds with the camera tilted by 3°: 0.5 and 0.9); aiming at 1.0 left those at 1.66, at
0.85 every benchmark set's queries sit between 0.5 and 1.5 (BENCHMARKS.md, the calibration row)."""
MAX_RATIO = 2.0
"""The largest held-out error / std the factor may leave (few samples: keep the tail inside 3σ)."""
TAIL_SLACK_M = 0.02
"""Metres of a held-out error the tail bound (:data:`MAX_RATIO`) does not count: a promise is
``3σ + 5 cm``, so an error of a few centimetres says nothing against a smaller std (KITTI seq 1,
map every 2nd frame: the largest held-out ratio 1.8 was 2.1 cm against a 1.2 cm std)."""
MIN_SCALE = 0.25
"""The std is never shrunk more than 4 times."""
GROW_ABOVE_MEDIAN = 1.25
"""A median held-out error / std above this grows the std until the median reaches it. Held-out
images overstate a query's error (their neighbours are further away), so below it the std is only
ever shrunk; RootSIFT maps of every benchmark set measure 0.26-1.16 (their queries 0.3-0.7). The
learned types' maps of the Strecha facades measured up to 3.3 (XFeat 1.04-1.89, LighterGlue
1.47-2.15, ALIKED + LightGlue 1.81-3.27), and their queries agreed: ALIKED's same-session queries
ran at a median 1.7-1.9, and one of its cross-session successes was 4.0 stds off (BENCHMARKS.md,
"Learned features")."""
MAX_SCALE = 4.0
"""The std is never grown more than 4 times."""
MIN_SAMPLES = 5
"""Fewer held-out successes than this is no measurement (the factor stays 1)."""
MAX_HELD_OUT = 16
"""Map images held out at most (spread over the map)."""


@dataclass(frozen=True)
class StdCalibration:
    """The map's measured factor on the modelled std.

    Attributes:
        scale: the factor (1: the model's std as it is).
        samples: held-out map images whose pose counted.
        held_out: map images held out.
        median_ratio: median error / std of the samples before the factor.
        max_ratio: the largest.
        doubtful: held-out map images not counted because their stored pose disagrees with
            their images (no answer to measure against; :mod:`planarloc.localize.held_out`):
            worth a look at the map's poses there.
    """

    scale: float
    samples: int
    held_out: int
    median_ratio: float
    max_ratio: float
    doubtful: tuple[str, ...] = ()

    def summary(self) -> str:
        text = (
            f"position std x {self.scale:.2g} (held-out map images: median error / std "
            f"{self.median_ratio:.2g}, largest {self.max_ratio:.2g}, over {self.samples} of {self.held_out})"
        )
        if self.doubtful:
            more = f" and {len(self.doubtful) - 3} more" if len(self.doubtful) > 3 else ""
            text += (
                f"; not counted, their stored poses disagree with their images: "
                f"{', '.join(self.doubtful[:3])}{more}"
            )
        return text


def scale_from_ratios(ratios: np.ndarray, tail_ratios: np.ndarray | None = None) -> float:
    """The factor on the std from held-out ``ratios`` (N,) (error / std): shrink the std until
    the median reaches :data:`TARGET_MEDIAN_RATIO`, never so far that the largest of
    ``tail_ratios`` (N,) (default: ``ratios``; :func:`tail_ratios` discounts the promise's slack)
    exceeds :data:`MAX_RATIO`, never below :data:`MIN_SCALE`; 1 with fewer than
    :data:`MIN_SAMPLES` ratios.

    It grows the std only where the median exceeds :data:`GROW_ABOVE_MEDIAN` (then to bring the
    median to it, at most :data:`MAX_SCALE` times): a held-out image is localized without itself,
    its neighbours further away than a query's among the map images, so it overstates the errors
    of the queries the map covers (KITTI seq 2, map every 4th frame: held-out median 1.07, largest
    3.3; the queries between them 0.46 and 1.84 without a factor; ``fountain_p11``: 1.16 against
    0.67), and a median a little above the target says little against the std."""
    ratios = np.asarray(ratios, dtype=float)
    tail = ratios if tail_ratios is None else np.asarray(tail_ratios, dtype=float)
    keep = np.isfinite(ratios) & np.isfinite(tail)
    ratios, tail = ratios[keep], tail[keep]
    if len(ratios) < MIN_SAMPLES:
        return 1.0
    median = float(np.median(ratios))
    if median > GROW_ABOVE_MEDIAN:
        return float(min(median / GROW_ABOVE_MEDIAN, MAX_SCALE))
    scale = max(median / TARGET_MEDIAN_RATIO, float(tail.max()) / MAX_RATIO, MIN_SCALE)
    return float(min(scale, 1.0))


def tail_ratios(errors_m: np.ndarray, stds_m: np.ndarray) -> np.ndarray:
    """``(error − TAIL_SLACK_M) / std`` (N,) of held-out ``errors_m`` and ``stds_m`` (N,), at least 0."""
    return np.maximum(np.asarray(errors_m, float) - TAIL_SLACK_M, 0.0) / np.asarray(stds_m, float)


def store_std_calibration(db: MapDatabase, calibration: StdCalibration | None) -> None:
    """Store (or, for None, clear) the map's std calibration."""
    db.set_meta(STD_CALIBRATION_META, "" if calibration is None else json.dumps(asdict(calibration)))


def mark_std_calibration_stale(db: MapDatabase) -> None:
    """The map changed: its calibration no longer counts and is due (:func:`std_calibration_due`)."""
    db.set_meta(STD_CALIBRATION_META, STALE)


def std_calibration_due(db: MapDatabase) -> bool:
    """Whether the map's calibration is still to be measured (never, or changed since)."""
    return db.get_meta(STD_CALIBRATION_META) in (None, STALE)


def load_std_calibration(db: MapDatabase) -> StdCalibration | None:
    """The stored calibration; None for a map without one (or a stale one)."""
    text = db.get_meta(STD_CALIBRATION_META)
    if not text or text == STALE:
        return None
    try:
        fields = json.loads(text)
        out = StdCalibration(**{**fields, "doubtful": tuple(fields.get("doubtful", ()))})
    except (TypeError, ValueError, json.JSONDecodeError):
        logger.warning("%s: unreadable %s meta value ignored", db.path, STD_CALIBRATION_META)
        return None
    if not (math.isfinite(out.scale) and MIN_SCALE <= out.scale <= MAX_SCALE):
        logger.warning("%s: %s scale %r out of range ignored", db.path, STD_CALIBRATION_META, out.scale)
        return None
    return out
