"""Options of the robust absolute pose estimator: one frozen dataclass, documented defaults."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from enum import Enum
from typing import TypeVar

import numpy as np

from planarloc.geometry.validation import InputError, check_integer, check_positive


class Method(str, Enum):
    """Hypothesis families (paper Sec. IV and its baselines, Sec. V).

    ``auto`` (default): the planar 2p1p on gravity-levelled bearings *and* 6DoF 5-point
    hypotheses (Nistér) in one problem; the refined pose of lowest cost wins and its
    :attr:`PoseEstimate.model` says whether the planar model held. The others are the
    paper's methods by name, for reproduction.
    """

    AUTO = "auto"
    P2P1 = "2p1p"
    P2P2 = "2p2p"
    NISTER = "5p5p-nister"
    STEWENIUS = "5p5p-stewenius"
    EIGHT = "8p8p"


class Structure(str, Enum):
    """Which constraints beyond 2D-2D are used.

    ``tracks`` (default): also triangulate query keypoints matched in two or more references
    (whose poses are known) and use the 2D-3D constraints — removes the collinear degeneracy
    of roads and corridors (KITTI: 100 % within 0.25 m instead of 0 %), still with no pre-built
    3D model. ``none``: the paper's 2D-2D constraints only (plus ``ref_points3d`` if given).
    """

    NONE = "none"
    TRACKS = "tracks"


_E = TypeVar("_E", Method, Structure)

_FINITE_FIELDS = (
    "threshold_px",
    "rcheck_deg",
    "consistency_deg",
    "max_position_std_m",
    "map_rotation_std_deg",
    "map_position_std_m",
    "min_collinearity_ratio",
    "track_min_angle_deg",
    "planar_tolerance_deg",
    "max_reference_shift_std",
    "std_scale",
)


@dataclass(frozen=True)
class RansacOptions:
    """Options of :func:`planarloc.estimate_absolute_pose`.

    Attributes:
        max_iterations: upper bound on minimal samples drawn. A search that stops on it before
            it could rule out a pose of more support than its own gives ``search_incomplete``
            (:mod:`planarloc.robust.search_confidence`).
        min_iterations: lower bound; set both to 100 to reproduce the paper's fixed 100.
        threshold_px: inlier threshold on the Sampson error of 2D-2D matches, in pixels.
        threshold_3d_px: inlier threshold on the reprojection error of 2D-3D constraints, in
            pixels; None (default) is ``2 · threshold_px``: a point triangulated from two map
            images carries the keypoint errors of both (the triangulate-and-PnP peer of NOTES.md
            uses 4 px).
        confidence: RANSAC confidence for adaptive termination.
        rcheck_deg: Rcheck threshold ``e_th`` of eq. (12), degrees (2p2p and baselines).
        consistency_deg: consistency check threshold ``α_th``, degrees.
        structure: ``"tracks"`` (default) or ``"none"``, the paper's 2D-2D mode (see
            :class:`Structure`).
        refine: run the final robust 6DoF refinement (and local optimisation).
        local_optimization: refine the best model on its inliers whenever it improves.
        min_inliers: fewer inliers than this in total is a failure.
        max_position_std_m: a refined position whose standard deviation (largest axis of
            its covariance, inflated for per-reference correlation and checked by leaving
            out each reference) exceeds this is reported as ``degenerate_scale``, not as a
            pose. 0.3 m keeps every success within 1 m when the std is calibrated
            (3·std + 0.05 m); raise it to accept coarser poses.
        map_rotation_std_deg, map_position_std_m: uncertainty of the map's reference poses
            (rotation in degrees, centre in metres), propagated into ``position_std_m``; map
            errors are systematic per reference and near-collinear geometry amplifies them.
            Set both to 0 for perfect (e.g. synthetic) maps. The Localizer replaces them with
            the map's own measurement (:mod:`planarloc.map.pose_accuracy`) where it has one.
        map_prior_measured: the two map stds above were measured on the map's images (set by
            the Localizer). For a pose carried by 2D-3D constraints the map errors are then
            modelled, and the linearised covariance is not inflated for residuals correlated
            within a reference (:func:`planarloc.robust.observability.correlation_inflation`),
            which stands in for them when the prior is only assumed. A pose on 2D-2D
            constraints alone keeps the inflation, and ``assumed_map_prior`` as a floor of the
            map stds it propagates.
        assumed_map_prior: the map stds assumed before the measurement, ``(rotation degrees,
            position metres)`` (set by the Localizer with ``map_prior_measured``).
        std_scale: factor on the modelled position covariance's std of a pose carried by 2D-3D
            constraints under a measured map prior, measured on the map's own images held out
            in turn (:mod:`planarloc.localize.std_calibration`; set by the Localizer, 1 without
            that measurement). The leave-one-reference-out spread and rivals are not scaled.
        min_collinearity_ratio: with fewer than ``min_inliers`` 2D-3D inliers, the query
            centre and the centres of the references with inliers must not lie on one line:
            the ratio of the second to the first singular value of the centred centres must
            be at least this. Otherwise the query position along the line is unobservable
            from 2D-2D constraints and ``degenerate_scale`` is returned (straight corridors
            and roads; see NOTES.md, KITTI).
        track_min_angle_deg: minimum triangulation angle for a track's 3D point.
        planar_tolerance_deg: the planar model "holds" for a refined pose whose implied
            gravity is within this angle of the query's gravity and whose elevation above or
            below the references' level plane is within this angle
            (:func:`planarloc.robust.observability.planar_fit`).
        cross_check: a method chosen by name also runs the search of the other motion model, as
            ``"auto"`` does. With ``"2p1p"`` or ``"2p2p"`` a 6DoF (5-point) search: the answer
            is ``planar_model_violated`` instead of the planar pose when a 6DoF pose far from it
            explains the matches better (tilted query, query off the map's plane). With the 6DoF
            baselines a planar 2p1p search: its pose, where it explains the matches about as
            well from elsewhere, is a rival that bounds the uncertainty (cross-session facades
            with repeated windows gave 6DoF poses 10-40 m off with 40-130 inliers). A planar pose
            on few inliers is also searched for a second time (``auto`` too; the better pose
            wins, one elsewhere at about its cost is a rival). Turning it off reproduces the
            paper's methods and timing, without the guarantee.
        max_reference_shift_std: verification. Each supporting reference is left out in
            turn and the pose refined again; the spread of those poses is a floor of the
            position std, and a pose that moves by more than this many standard deviations
            (the std floored by the spread) when one reference is removed is reported as
            ``inconsistent_references``. With three references under a pose on many inliers
            the spread is that of the two-image problems left, the scale's minimum: it floors
            the std up to ``max_position_std_m`` and does not refuse the pose.
        seed: seed of the ``numpy.random.Generator`` used for sampling.
    """

    max_iterations: int = 1000
    min_iterations: int = 100
    threshold_px: float = 2.0
    threshold_3d_px: float | None = None
    confidence: float = 0.9999
    rcheck_deg: float = 2.0
    consistency_deg: float = 2.0
    structure: Structure | str = Structure.TRACKS
    refine: bool = True
    local_optimization: bool = True
    min_inliers: int = 10
    max_position_std_m: float = 0.3
    map_rotation_std_deg: float = 0.1
    map_position_std_m: float = 0.02
    map_prior_measured: bool = False
    assumed_map_prior: tuple[float, float] | None = None
    std_scale: float = 1.0
    min_collinearity_ratio: float = 0.01
    track_min_angle_deg: float = 1.0
    planar_tolerance_deg: float = 1.5
    cross_check: bool = True
    max_reference_shift_std: float = 6.0
    seed: int | None = 0

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "structure", parse_choice(Structure, self.structure, "RansacOptions.structure")
        )
        for name in ("max_iterations", "min_iterations", "min_inliers"):
            check_integer(f"RansacOptions.{name}", getattr(self, name), 0)
        check_integer("RansacOptions.seed", self.seed, 0, allow_none=True)
        for name in _FINITE_FIELDS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise InputError(f"RansacOptions.{name}: expected a number, got {v!r}")
            if not math.isfinite(v) and name != "max_position_std_m":
                raise InputError(f"RansacOptions.{name}: must be finite, got {v}")
        check_positive("RansacOptions.threshold_3d_px", self.threshold_3d_px, allow_none=True)
        if not (1 <= self.min_iterations <= self.max_iterations):
            raise InputError(
                f"RansacOptions: need 1 <= min_iterations <= max_iterations, got {self.min_iterations}, "
                f"{self.max_iterations}"
            )
        for name in (
            "threshold_px",
            "rcheck_deg",
            "consistency_deg",
            "max_position_std_m",
            "planar_tolerance_deg",
            "max_reference_shift_std",
            "std_scale",
        ):
            if not getattr(self, name) > 0:
                raise InputError(f"RansacOptions.{name}: must be > 0, got {getattr(self, name)}")
        for name in (
            "map_rotation_std_deg",
            "map_position_std_m",
            "min_collinearity_ratio",
            "track_min_angle_deg",
        ):
            if not getattr(self, name) >= 0:
                raise InputError(f"RansacOptions.{name}: must be >= 0, got {getattr(self, name)}")
        if self.min_collinearity_ratio > 1:
            raise InputError(
                f"RansacOptions.min_collinearity_ratio: a singular value ratio, must be <= 1, "
                f"got {self.min_collinearity_ratio}"
            )
        if not (0.0 < self.confidence < 1.0):
            raise InputError(f"RansacOptions.confidence: must be in (0, 1), got {self.confidence}")

    def with_iterations(self, iterations: int) -> RansacOptions:
        """These options with exactly ``min(iterations, max_iterations)`` RANSAC iterations (a
        short search); ``iterations`` >= 1. A copy that is not validated again (only the two
        budgets change, to valid values): ``dataclasses.replace`` would re-run ``__post_init__``,
        ~20 µs on every estimate that runs a short check."""
        n = min(int(iterations), self.max_iterations)
        if n < 1:
            raise InputError(f"RansacOptions.with_iterations: need >= 1 iteration, got {iterations}")
        out = copy.copy(self)
        object.__setattr__(out, "min_iterations", n)
        object.__setattr__(out, "max_iterations", n)
        return out


def reprojection_threshold_px(options: RansacOptions) -> float:
    """The 2D-3D inlier threshold τ₃ of ``options`` (``threshold_3d_px``, default 2τ)."""
    return 2.0 * options.threshold_px if options.threshold_3d_px is None else float(options.threshold_3d_px)


def parse_choice(kind: type[_E], value: _E | str, name: str) -> _E:
    """``value`` as a member of the enum ``kind`` (:class:`Method`, :class:`Structure`): a member, or
    its value as a string (a CLI argument, a form field, a ROS parameter). The one place where a
    front door's text becomes an enum; configurations hold the members.

    Raises:
        InputError: a value that is not one of ``kind``'s, naming ``name`` and the choices.
    """
    try:
        return kind(getattr(value, "value", value))
    except ValueError:
        names = ", ".join(str(m.value) for m in kind)
        raise InputError(f"{name}: expected one of {names}, got {value!r}") from None


def parse_method(method: Method | str) -> Method:
    """:func:`parse_choice` for a :class:`Method`."""
    return parse_choice(Method, method, "method")


def parse_structure(structure: Structure | str) -> Structure:
    """:func:`parse_choice` for a :class:`Structure`."""
    return parse_choice(Structure, structure, "structure")
