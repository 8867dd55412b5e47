"""Settings of a stream (:class:`SequenceConfig`), shared by the stream localizer
(:mod:`planarloc.localize.sequence`) and its fixes (:mod:`planarloc.localize.fixes`); the CLI
takes its defaults from here."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from planarloc.geometry.validation import InputError, check_integer, check_positive
from planarloc.localize.tracking import TrackerOptions
from planarloc.robust.relative_pose import MODELS

#: where fixes are computed (``SequenceConfig.fixes``)
FIX_MODES = ("background", "wait")
#: the stream settings every front door names alike (its options' or parameters' attributes)
SHARED_SETTINGS = ("window", "local_top_n", "vo_model", "kidnap_confirmations", "fixes")


@dataclass(frozen=True)
class SequenceConfig:
    """Settings of :class:`planarloc.localize.sequence.SequenceLocalizer`; the CLI uses these defaults.

    Attributes:
        fixes: ``"background"`` (a worker thread; the frame path does not wait) or ``"wait"``
            (inside ``SequenceLocalizer.step``, deterministic; :mod:`planarloc.localize.sequence`).
        fix_every: frames between two fix jobs at least (``"background"``: also only when the
            worker is idle).
        fix_delay: ``"wait"`` only: frames between a fix job and the fusion of its result (0:
            the same frame).
        max_fix_lag_s: ``"background"`` only: a frame more than this much stream time (stamps)
            after the frame of the fix in flight waits for that fix. At camera rate on 2 cores a
            fix comes back within a frame or two and nothing waits; frames that come faster than
            the camera (a recording replayed as fast as it goes, a stalled worker) would
            otherwise be chained by odometry ever farther from their last fix.
        max_latency_s: a frame whose pose comes later than this after its arrival is ``late``.
        fix_resize_max: fixes detect features on the frame downscaled to at most this many pixels
            (None: as the map's single-frame queries; :mod:`planarloc.localize.fixes`).
        window: poses kept in the sliding-window pose graph.
        local_top_n: map images nearest to the prediction used for the fix (no VLAD).
        local_radius_m: map images farther than ``max(local_radius_m, 3 σ)`` from the predicted
            centre are not candidates; ``local_max_angle_deg`` likewise for viewing directions.
        gate_probability: χ²(6) quantile of the Mahalanobis gate.
        fix_std_scale, min_fix_std_m, pixel_std, min_rotation_std_deg: covariance of a fix
            (:mod:`planarloc.localize.fixes`).
        fix_std_scale_2d, min_inliers_3d: a fix with fewer than ``min_inliers_3d`` 2D-3D
            inliers (the paper's 2D-2D constraints only) has its position std scaled by
            ``fix_std_scale_2d`` instead: on forward motion its ``position_std_m`` is optimistic
            by up to ~10x (KITTI: 3-4 m errors reported with 0.1-0.3 m std).
        odometry_translation_std, odometry_min_std_m: wheel-odometry translation std, as a
            fraction of the distance travelled plus a floor (metres, per frame).
        odometry_rotation_std, odometry_min_rotation_std_deg: the same for rotation.
        vo_model: ``"planar"``, ``"6dof"`` or ``"auto"`` (see :func:`estimate_relative_pose`).
        vo_direction_std_deg, vo_rotation_std_deg: visual-odometry direction and rotation std.
        vo_scale_std: relative std of the speed used to scale visual odometry.
        vo_first_scale_std: the same while no two fixes have measured the speed yet (the first
            frames of a stream, after a re-initialisation: a kidnapped robot may move otherwise).
        point_fix_min_std_m, point_fix_rotation_std_deg, point_fix_std_per_frame: a pose from
            tracked world points (PnP) has the position std ``point_fix_min_std_m · g`` and the
            rotation std ``point_fix_rotation_std_deg · g``, ``g = (1 + point_fix_std_per_frame · k)
            · sqrt(max(1, 60 / n))`` after ``k`` frames of tracking with ``n`` inlier points (the
            same points in every frame: their errors do not average out, and tracks drift).
        tracking: the corner tracker's settings
            (:class:`~planarloc.localize.tracking.TrackerOptions`; its ``model`` is ``vo_model``).
        max_speed_mps: std of the distance per second while the speed is unknown.
        lost_std_m: a prediction with a position std above this is no guide: fixes go to global
            retrieval, the frame waits for the fix in flight, and it is ``lost``.
        max_pose_std_m: a frame whose position std (fused or predicted) is above this is
            ``lost``: a pose that keeps its promise (within 3 std + 5 cm) is then less than 1 m
            off (0.95 m at the default 0.3 m).
        localized_std_m: a frame whose position std is above this is not ``localized`` (at most
            ``predicted``).
        kidnap_confirmations: consistent rejected fixes needed to re-initialise.
        refix_radius_m: a global fix is re-estimated from the map images nearest to it; the
            second estimate replaces the first when within this distance.
        frame_period_s: time between frames of a stream without stamps (the CLI's image lists
            without timestamps).
        single_thread_blas: while the stream is open, run the BLAS library with one thread
            (process-wide, restored by the last ``SequenceLocalizer.close``;
            :mod:`planarloc.localize.sequence`).
    """

    fixes: str = "background"
    fix_every: int = 1
    fix_delay: int = 0
    max_fix_lag_s: float = 0.3
    max_latency_s: float = 0.1
    fix_resize_max: int | None = 640
    window: int = 16
    local_top_n: int = 2
    local_radius_m: float = 15.0
    local_max_angle_deg: float = 60.0
    gate_probability: float = 0.999
    fix_std_scale: float = 1.0  # factor on a fix's position_std_m
    fix_std_scale_2d: float = 5.0
    min_inliers_3d: int = 10
    min_fix_std_m: float = 0.03  # floor of a fix's position std
    pixel_std: float = 1.0  # keypoint noise behind a fix's rotation std, px
    min_rotation_std_deg: float = 0.2  # floor of a fix's rotation std
    odometry_translation_std: float = 0.05
    odometry_min_std_m: float = 0.02
    odometry_rotation_std: float = 0.05  # fraction of the angle turned
    odometry_min_rotation_std_deg: float = 0.3
    vo_model: str = "auto"
    vo_direction_std_deg: float = 3.0
    vo_rotation_std_deg: float = 0.5
    vo_scale_std: float = 0.05
    vo_first_scale_std: float = 0.3
    point_fix_min_std_m: float = 0.05
    point_fix_rotation_std_deg: float = 0.2
    point_fix_std_per_frame: float = 0.5
    tracking: TrackerOptions = TrackerOptions()
    max_speed_mps: float = 15.0
    lost_std_m: float = 1.0
    max_pose_std_m: float = 0.3
    localized_std_m: float = 0.3
    kidnap_confirmations: int = 2
    frame_period_s: float = 0.1
    refix_radius_m: float = 1.0
    single_thread_blas: bool = True

    def __post_init__(self) -> None:
        if self.fixes not in FIX_MODES:
            raise InputError(f"SequenceConfig.fixes: expected one of {FIX_MODES}, got {self.fixes!r}")
        minimum = {"window": 2, "local_top_n": 2, "kidnap_confirmations": 1, "fix_every": 1, "fix_delay": 0}
        for name, lo in minimum.items():
            check_integer(f"SequenceConfig.{name}", getattr(self, name), lo)
        check_integer("SequenceConfig.fix_resize_max", self.fix_resize_max, 16, allow_none=True)
        if not isinstance(self.tracking, TrackerOptions):
            raise InputError(
                f"SequenceConfig.tracking: expected TrackerOptions, got {type(self.tracking).__name__}"
            )
        if self.vo_model not in MODELS:
            raise InputError(f"SequenceConfig.vo_model: expected one of {MODELS}, got {self.vo_model!r}")
        if self.tracking.model not in (TrackerOptions().model, self.vo_model):
            raise InputError(
                f"SequenceConfig.tracking.model ({self.tracking.model!r}) is not used: the stream's "
                f"visual-odometry model is SequenceConfig.vo_model ({self.vo_model!r}); set that"
            )
        if not 0.5 < self.gate_probability < 1:
            raise InputError(
                f"SequenceConfig.gate_probability: expected a probability in (0.5, 1), "
                f"got {self.gate_probability}"
            )
        for name in (
            "max_fix_lag_s",
            "max_latency_s",
            "local_radius_m",
            "local_max_angle_deg",
            "fix_std_scale",
            "fix_std_scale_2d",
            "min_fix_std_m",
            "pixel_std",
            "min_rotation_std_deg",
            "odometry_translation_std",
            "odometry_min_std_m",
            "odometry_rotation_std",
            "odometry_min_rotation_std_deg",
            "vo_direction_std_deg",
            "vo_rotation_std_deg",
            "vo_scale_std",
            "vo_first_scale_std",
            "point_fix_min_std_m",
            "point_fix_std_per_frame",
            "point_fix_rotation_std_deg",
            "max_speed_mps",
            "lost_std_m",
            "max_pose_std_m",
            "localized_std_m",
            "frame_period_s",
            "refix_radius_m",
        ):
            check_positive(f"SequenceConfig.{name}", getattr(self, name))

    @property
    def tracker(self) -> TrackerOptions:
        """The corner tracker's options."""
        return dataclasses.replace(self.tracking, model=self.vo_model)


def sequence_config_from(
    source: object, names: Iterable[str] = SHARED_SETTINGS, **more: Any
) -> SequenceConfig:
    """A :class:`SequenceConfig` of the attributes ``names`` of ``source`` (an argparse namespace,
    a node's parameters) and of ``more``; the rest keeps its default."""
    return SequenceConfig(**{name: getattr(source, name) for name in names}, **more)
