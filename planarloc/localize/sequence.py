"""Localize a camera stream: motion between frames, prediction, gated absolute fixes, recovery.

:class:`SequenceLocalizer` takes one frame at a time (:meth:`SequenceLocalizer.step`) and
returns a :class:`SequenceEstimate` for every frame: a pose with a (6, 6) covariance and a
status — ``localized`` (an absolute fix was accepted in this frame), ``predicted`` (no usable
fix; the pose comes from the motion since the last fix and its position std is at most
``SequenceConfig.lost_std_m``) or ``lost`` (no pose yet, a prediction too uncertain to use, or
a prediction without measured motion that a global fix contradicts: the stream jumped).
A single contradicting fix does not make a frame ``lost`` (it is reported and the frame says
``kidnap_suspected``): one wrong fix is more likely than a kidnap.

Per frame:

1. **Motion** from the previous frame: wheel odometry when given (``odometry`` =
   ``cam_from_odom`` pose of this frame in the odometry frame, e.g. a TUM pose file), otherwise
   visual odometry between the two query frames (:func:`estimate_relative_pose`, the planar
   2-point solver, 6DoF when the planar model does not fit). Visual odometry has no scale: its
   translation is scaled by the speed measured over the last fixes (``SequenceConfig``
   documents the covariances). Without either, a constant-velocity guess with a large
   covariance.
2. **Prediction**: the new node of the sliding-window pose graph
   (:mod:`planarloc.robust.pose_graph`) with its marginal covariance.
3. **Absolute fix** against the map images nearest to the prediction (no global retrieval);
   global retrieval (VLAD, then again from the map images nearest to that fix) when there is
   no prediction, when it is too uncertain, or when the local attempt failed or was rejected.
4. **Gating**: the fix is accepted when its Mahalanobis distance to the prediction under the
   summed covariances passes the χ²(6) test; rejected fixes are reported, never used. If the
   motion came from visual odometry and two fixes (local and global) agree with each other and
   with a constant-velocity model, the visual-odometry factor is the outlier and is replaced.
5. **Fusion**: accepted fixes and motions are solved jointly in the window; the oldest node is
   marginalised into a prior.
6. **Recovery**: ``kidnap_confirmations`` consecutive rejected fixes that agree with each other
   (through the motion between them) re-initialise the window at the latest fix.

Covariance of an absolute fix (the single-frame estimator reports only ``position_std_m``,
the std along its worst axis): position ``(fix_std_scale · position_std_m)² I`` (floored at
``min_fix_std_m``); rotation ``σ_R² I`` with ``σ_R² = σ_px² / (f² N) + σ_map²`` — ``N`` bearings
with ``σ_px`` pixel noise fix a rotation to about ``σ_px / (f √N)`` radians, and the map's own
rotation error ``σ_map`` (``RansacOptions.map_rotation_std_deg``) adds to it — floored at
``min_rotation_std_deg``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from scipy.stats import chi2

from planarloc.features.extract import Features, extract_features
from planarloc.features.matching import match_features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.localize.localizer import Localizer
from planarloc.localize.query import ImageSource, Query
from planarloc.robust.pose_graph import (
    AbsoluteFactor,
    RelativeFactor,
    marginal_covariances,
    marginalize_first,
    so3_log,
    solve_pose_graph,
)
from planarloc.robust.relative_pose import MODELS, estimate_relative_pose
from planarloc.robust.result import PoseEstimate

logger = logging.getLogger(__name__)


#: visual-odometry speed: chord over this many of the latest fixes (see ``_update_speed``)
SPEED_FIXES = 5


class FrameStatus(str, Enum):
    LOCALIZED = "localized"
    PREDICTED = "predicted"
    LOST = "lost"


@dataclass(frozen=True)
class SequenceConfig:
    """Settings of :class:`SequenceLocalizer`; the CLI uses these defaults.

    Attributes:
        window: poses kept in the sliding-window pose graph.
        local_top_n: map images nearest to the prediction used for the fix (no VLAD).
        local_radius_m: map images farther than ``max(local_radius_m, 3 σ)`` from the predicted
            centre are not candidates; ``local_max_angle_deg`` likewise for viewing directions.
        gate_probability: χ²(6) quantile of the Mahalanobis gate.
        fix_std_scale, min_fix_std_m, pixel_std, min_rotation_std_deg: covariance of a fix
            (module docstring).
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
        max_speed_mps: std of the distance per second while the speed is unknown.
        lost_std_m: a frame whose position std (fused or predicted) is above this is ``lost``.
        kidnap_confirmations: consistent rejected fixes needed to re-initialise.
        refix_radius_m: a global fix is re-estimated from the map images nearest to it; the
            second estimate replaces the first when within this distance.
        frame_period_s: time between frames when stamps are not increasing (e.g. all zero).
    """

    window: int = 10
    local_top_n: int = 2
    local_radius_m: float = 15.0
    local_max_angle_deg: float = 60.0
    gate_probability: float = 0.999
    fix_std_scale: float = 2.0
    fix_std_scale_2d: float = 5.0
    min_inliers_3d: int = 10
    min_fix_std_m: float = 0.03
    pixel_std: float = 1.0
    min_rotation_std_deg: float = 0.2
    odometry_translation_std: float = 0.05
    odometry_min_std_m: float = 0.02
    odometry_rotation_std: float = 0.05
    odometry_min_rotation_std_deg: float = 0.3
    vo_model: str = "auto"
    vo_direction_std_deg: float = 3.0
    vo_rotation_std_deg: float = 0.5
    vo_scale_std: float = 0.3
    max_speed_mps: float = 15.0
    lost_std_m: float = 1.0
    kidnap_confirmations: int = 2
    frame_period_s: float = 0.1
    refix_radius_m: float = 1.0

    def __post_init__(self) -> None:
        for name in ("window", "local_top_n", "kidnap_confirmations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (2 if name != "kidnap_confirmations"
                                                                                     else 1):
                raise InputError(f"SequenceConfig.{name}: expected an integer >= 2 (>= 1 for confirmations), got {v!r}")
        if self.vo_model not in MODELS:
            raise InputError(f"SequenceConfig.vo_model: expected one of {MODELS}, got {self.vo_model!r}")
        if not 0.5 < self.gate_probability < 1:
            raise InputError(f"SequenceConfig.gate_probability: expected a probability in (0.5, 1), "
                             f"got {self.gate_probability}")
        for name in ("local_radius_m", "local_max_angle_deg", "fix_std_scale", "fix_std_scale_2d", "min_fix_std_m",
                     "pixel_std",
                     "min_rotation_std_deg", "odometry_translation_std", "odometry_min_std_m",
                     "odometry_rotation_std", "odometry_min_rotation_std_deg", "vo_direction_std_deg",
                     "vo_rotation_std_deg", "vo_scale_std", "max_speed_mps", "lost_std_m", "frame_period_s",
                     "refix_radius_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"SequenceConfig.{name}: expected a finite number > 0, got {v!r}")


@dataclass
class SequenceEstimate:
    """What :meth:`SequenceLocalizer.step` returns for one frame.

    Attributes:
        stamp: the frame's time in seconds.
        status: ``"localized"``, ``"predicted"`` or ``"lost"`` (:class:`FrameStatus`).
        pose: ``cam_from_world`` (the fused pose, or the prediction); None only while no fix
            was ever accepted.
        covariance: (6, 6) of ``(rotation [rad], camera centre [m])`` in the world frame; inf
            without a pose.
        position_std_m: sqrt of the largest eigenvalue of the position block (inf: no pose).
        rotation_std_deg: the same for rotation, in degrees.
        fix: the absolute estimate of this frame (the last one tried), or None.
        fix_status: ``"accepted"``, ``"rejected"`` (failed the gate), ``"failed"`` (the
            single-frame estimator failed) or ``"none"`` (not attempted).
        rejected: one dict per rejected fix: centre, Mahalanobis distance², retrieval kind.
        mahalanobis_sq: distance² of the accepted or last rejected fix to the prediction.
        motion_source: ``"odometry"``, ``"visual"``, ``"constant"``, ``"none"`` (first frame) or
            ``"visual_rejected"`` (visual odometry contradicted an accepted fix and was replaced
            by the constant-velocity model).
        motion_model: ``"planar"`` / ``"6dof"`` for visual odometry, else empty.
        global_retrieval: whether global (VLAD) retrieval was used.
        kidnap_suspected: a rejected fix is waiting for confirmation.
        reinitialized: the window was reset from global localization in this frame.
        seconds: wall time of the step.
    """

    stamp: float
    status: str
    pose: Pose | None
    covariance: np.ndarray
    position_std_m: float
    rotation_std_deg: float
    fix: PoseEstimate | None = None
    fix_status: str = "none"
    rejected: list[dict] = field(default_factory=list)
    mahalanobis_sq: float = float("nan")
    motion_source: str = "none"
    motion_model: str = ""
    global_retrieval: bool = False
    kidnap_suspected: bool = False
    reinitialized: bool = False
    seconds: float = 0.0

    @property
    def success(self) -> bool:
        """A pose the caller may use: ``localized`` or ``predicted``."""
        return self.pose is not None and self.status != FrameStatus.LOST.value

    def to_dict(self) -> dict:
        d = {
            "stamp": self.stamp, "success": self.success, "status": self.status,
            "position_std_m": _finite_or_none(self.position_std_m),
            "rotation_std_deg": _finite_or_none(self.rotation_std_deg),
            "fix_status": self.fix_status, "rejected": self.rejected,
            "mahalanobis_sq": _finite_or_none(self.mahalanobis_sq),
            "motion_source": self.motion_source, "motion_model": self.motion_model,
            "global_retrieval": self.global_retrieval, "kidnap_suspected": self.kidnap_suspected,
            "reinitialized": self.reinitialized, "seconds": self.seconds,
            "fix": None if self.fix is None else self.fix.to_dict(),
        }
        if self.pose is not None:
            d["quat_wxyz"] = [float(v) for v in self.pose.quat_wxyz]
            d["t"] = [float(v) for v in self.pose.t]
            d["covariance"] = np.where(np.isfinite(self.covariance), self.covariance, None).tolist()
        return d


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _stds(cov: np.ndarray) -> tuple[float, float]:
    if not np.all(np.isfinite(cov)):
        return float("inf"), float("inf")
    rot = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0)))
    pos = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
    return pos, float(np.degrees(rot))


def pose_difference(a: Pose, b: Pose) -> np.ndarray:
    """(6,) ``(log(R_a R_bᵀ), c_a − c_b)``: ``a`` in the tangent space of ``b`` (pose-graph order)."""
    return np.concatenate([so3_log((a.R @ b.R.T)[None])[0], a.center - b.center])


def mahalanobis_sq(a: Pose, cov_a: np.ndarray, b: Pose, cov_b: np.ndarray) -> float:
    """Squared Mahalanobis distance of two independent pose estimates (covariances (6, 6),
    :func:`pose_difference` order)."""
    e = pose_difference(a, b)
    S = cov_a + cov_b
    try:
        return float(e @ np.linalg.solve(S, e))
    except np.linalg.LinAlgError:
        return float("inf")


def _motion_covariance(d: np.ndarray, along_std: float, across_std: float, rot_std: float) -> np.ndarray:
    """(6, 6) covariance of a motion whose centre displacement ``d`` has ``along_std`` along
    its direction and ``across_std`` across it."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * rot_std**2
    n = np.linalg.norm(d)
    u = d / n if n > 1e-9 else np.zeros(3)
    P = np.outer(u, u)
    cov[3:, 3:] = along_std**2 * P + across_std**2 * (np.eye(3) - P)
    if n <= 1e-9:
        cov[3:, 3:] = np.eye(3) * along_std**2
    return cov


@dataclass
class _Candidate:
    """A rejected fix waiting for confirmation, and the motion since its frame."""

    pose: Pose
    covariance: np.ndarray
    count: int
    cur_from_cand: Pose = field(default_factory=Pose.identity)
    motion_cov: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


@dataclass(frozen=True)
class Motion:
    """The motion since the previous frame, ``cur_from_prev``, with its (6, 6) covariance.

    ``source``: ``"odometry"``, ``"visual"``, ``"constant"``, ``"none"`` (first frame) or
    ``"visual_rejected"``; ``model``: ``"planar"`` / ``"6dof"`` for visual odometry, else empty.
    """

    cur_from_prev: Pose
    covariance: np.ndarray
    source: str
    model: str = ""


@dataclass(frozen=True)
class Prediction:
    """The pose of the new frame predicted from the last one and the motion (``pose`` None:
    nothing to predict from; ``covariance`` inf then)."""

    pose: Pose | None
    covariance: np.ndarray
    motion: Motion
    position_std_m: float
    usable: bool  # a pose whose position std is at most SequenceConfig.lost_std_m


@dataclass(frozen=True)
class FixAttempt:
    """One absolute fix of a frame: the single-frame estimate, its covariance (None: failed or
    without a usable std), the retrieval that gave its references, its distance to the prediction."""

    estimate: PoseEstimate
    covariance: np.ndarray | None
    global_retrieval: bool
    mahalanobis_sq: float = float("nan")

    @property
    def pose(self) -> Pose:
        assert self.estimate.pose is not None  # only read for attempts with a covariance
        return self.estimate.pose

    def report(self) -> dict:
        """The entry of :attr:`SequenceEstimate.rejected`."""
        return {"center": [float(v) for v in self.pose.center], "mahalanobis_sq": self.mahalanobis_sq,
                "retrieval": "global" if self.global_retrieval else "local"}


@dataclass
class FixOutcome:
    """What the absolute fixes of one frame gave: the accepted pose and covariance (None: no
    fix accepted), the rejected attempts, the last estimate tried and its status."""

    accepted: tuple[Pose, np.ndarray] | None = None
    rejected: list[FixAttempt] = field(default_factory=list)
    last: PoseEstimate | None = None
    status: str = "none"
    mahalanobis_sq: float = float("nan")
    global_retrieval: bool = False


class SequenceLocalizer:
    """Localizes an ordered camera stream against a map, one frame per :meth:`step`.

    A step runs the stages of the module docstring, each a method with a named result:
    :meth:`_motion` (:class:`Motion`), :meth:`_predict` (:class:`Prediction`), :meth:`_fixes`
    (:class:`FixOutcome`), :meth:`_reject_visual_odometry`, :meth:`_track_kidnap` and
    :meth:`_fuse` (the frame's status).

    Args:
        localizer: a single-frame :class:`Localizer` (its config sets method and structure).
        config: :class:`SequenceConfig`.

    Example:
        >>> seq = SequenceLocalizer(Localizer("kitti.db"))                   # doctest: +SKIP
        >>> for image, stamp in stream:                                     # doctest: +SKIP
        ...     est = seq.step(image, camera, stamp)
        ...     print(est.status, est.pose.center if est.pose else None, est.position_std_m)
    """

    def __init__(self, localizer: Localizer, config: SequenceConfig | None = None) -> None:
        if not isinstance(localizer, Localizer):
            raise InputError(f"localizer: expected a planarloc Localizer, got {type(localizer).__name__}")
        self.localizer = localizer
        self.config = config or SequenceConfig()
        posed = localizer.map_images
        self._map_names = [p.name for p in posed]
        self._map_centers = np.array([p.cam_from_world.center for p in posed]).reshape(-1, 3)
        self._map_R = np.array([p.cam_from_world.R for p in posed]).reshape(-1, 3, 3)
        self._gate = float(chi2.ppf(self.config.gate_probability, 6))
        self._map_rotation_std = np.radians(localizer.config.ransac.map_rotation_std_deg)
        self.reset()

    def reset(self) -> None:
        """Forget the stream (e.g. before a new sequence)."""
        self._poses: list[Pose] = []
        self._stamps: list[float] = []
        self._localized: list[bool] = []
        self._absolute: list[AbsoluteFactor] = []
        self._relative: list[RelativeFactor] = []
        self._cov = np.full((6, 6), np.inf)
        self._prev: tuple[Features, Camera, float, Pose | None] | None = None
        self._speed: float | None = None
        self._candidate: _Candidate | None = None
        self._fix_centers: list[tuple[float, np.ndarray]] = []

    # ---- motion ---------------------------------------------------------------------------
    def _dt(self, stamp: float) -> float:
        dt = stamp - self._prev[2] if self._prev is not None else 0.0
        return dt if dt > 0 else self.config.frame_period_s

    def _motion(self, features: Features, camera: Camera, stamp: float, odometry: Pose | None) -> Motion:
        """The motion since the previous frame (odometry, else visual odometry, else constant velocity)."""
        cfg = self.config
        prev_features, prev_camera, _, prev_odometry = self._prev  # type: ignore[misc]
        dt = self._dt(stamp)
        if odometry is not None and prev_odometry is not None:
            motion = odometry @ prev_odometry.inverse()
            d = motion.inverse().t
            dist = float(np.linalg.norm(d))
            angle = float(np.linalg.norm(so3_log(motion.R[None])[0]))
            along = cfg.odometry_translation_std * dist + cfg.odometry_min_std_m
            rot = cfg.odometry_rotation_std * angle + np.radians(cfg.odometry_min_rotation_std_deg)
            return Motion(motion, _motion_covariance(d, along, along, rot), "odometry")
        vo = None
        if len(features) and len(prev_features):
            m = match_features(features, prev_features, ratio=self.localizer.config.ratio)
            if len(m) >= 15:
                vo = estimate_relative_pose(prev_camera, camera, prev_features.keypoints[m[:, 1]],
                                            features.keypoints[m[:, 0]], model=cfg.vo_model)
        if vo is not None and vo.success:
            u = vo.pose.inverse().t                   # direction of the centre of cur in prev's frame
            if self._speed is None:
                dist, along = 0.0, cfg.max_speed_mps * dt
            else:
                dist = self._speed * dt
                along = cfg.vo_scale_std * dist + 0.05
            across = dist * np.radians(cfg.vo_direction_std_deg) + 0.02
            motion = Pose(vo.pose.R, -vo.pose.R @ (u * dist))
            cov = _motion_covariance(u, along, across, np.radians(cfg.vo_rotation_std_deg))
            return Motion(motion, cov, "visual", vo.model)
        return self._constant_motion(dt)

    def _constant_motion(self, dt: float) -> Motion:
        """Constant velocity from the last two nodes, with a large covariance (a weak motion
        model: position std ``max_speed_mps · dt / 5`` plus half the step, rotation 20°)."""
        motion, d = Pose.identity(), np.zeros(3)
        if len(self._poses) >= 2 and self._speed is not None:
            last = self._poses[-1] @ self._poses[-2].inverse()
            d = last.inverse().t
            n = np.linalg.norm(d)
            if n > 1e-9:
                d = d / n * self._speed * dt
            motion = Pose(last.R, -last.R @ d)
        along = 0.5 * float(np.linalg.norm(d)) + 0.2 * self.config.max_speed_mps * dt
        return Motion(motion, _motion_covariance(d, along, along, np.radians(20.0)), "constant")

    def _predict(self, features: Features, camera: Camera, stamp: float, odometry: Pose | None) -> Prediction:
        """Stages 1-2: the motion since the previous frame and the new node of the window it predicts."""
        if not self._poses or self._prev is None:
            none = Motion(Pose.identity(), np.zeros((6, 6)), "none")
            return Prediction(None, np.full((6, 6), np.inf), none, float("inf"), False)
        motion = self._motion(features, camera, stamp, odometry)
        pose = motion.cur_from_prev @ self._poses[-1]
        n = len(self._poses)
        self._poses.append(pose)
        self._stamps.append(stamp)
        self._localized.append(False)
        self._relative.append(RelativeFactor(n - 1, n, motion.cur_from_prev, motion.covariance))
        cov = marginal_covariances(self._poses, self._absolute, self._relative)[-1]
        std, _ = _stds(cov)
        return Prediction(pose, cov, motion, std, std <= self.config.lost_std_m)

    def _carry_candidate(self, motion: Motion, stamp: float) -> None:
        """Move a kidnap candidate along with the motion. Wheel odometry is trusted across a
        kidnap check; visual odometry may be wrong exactly there, so agreeing fixes then need
        only agree within the weak motion model."""
        c = self._candidate
        if c is None:
            return
        c.cur_from_cand = motion.cur_from_prev @ c.cur_from_cand
        c.motion_cov = c.motion_cov + motion.covariance
        if motion.source != "odometry":
            c.motion_cov = c.motion_cov + self._constant_motion(self._dt(stamp)).covariance

    # ---- retrieval prior ------------------------------------------------------------------
    def references_near(self, pose: Pose, position_std_m: float) -> list[str] | None:
        """The ``local_top_n`` map images nearest to ``pose`` (distance plus 1 m per 30° of
        viewing-direction difference); None when fewer than 2 qualify (use global retrieval)."""
        cfg = self.config
        dist = np.linalg.norm(self._map_centers - pose.center, axis=1)
        cos = (np.einsum("nij,ij->n", self._map_R, pose.R) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        ok = (dist <= max(cfg.local_radius_m, 3.0 * position_std_m)) & (angle <= cfg.local_max_angle_deg)
        idx = np.flatnonzero(ok)
        if len(idx) < 2:
            return None
        score = dist[idx] + angle[idx] / 30.0
        return [self._map_names[i] for i in idx[np.argsort(score)[: cfg.local_top_n]]]

    # ---- absolute fixes -------------------------------------------------------------------
    def _fix(self, features: Features, camera: Camera, references: list[str] | None,
             gravity: np.ndarray | None) -> PoseEstimate:
        """Single-frame fix from ``references``; with None, global retrieval followed by a
        second estimate from the map images nearest to the first (nearer references, better
        conditioned geometry: on KITTI the 2 nearest map images give 2-5x smaller errors than
        the VLAD top 5), kept when it lies within ``refix_radius_m`` of the first."""
        est = self.localizer.localize_features(features, camera, references, gravity=gravity)
        if references is not None or not est.success or est.pose is None:
            return est
        near = self.references_near(est.pose, 0.0)
        cov = self.fix_covariance(est, camera)
        if near is None or cov is None or set(near) <= set(est.references):
            return est
        again = self.localizer.localize_features(features, camera, near, gravity=gravity)
        cov2 = self.fix_covariance(again, camera) if again.success and again.pose is not None else None
        if cov2 is not None and np.linalg.norm(again.pose.center - est.pose.center) <= self.config.refix_radius_m:
            return again
        return est

    def fix_covariance(self, est: PoseEstimate, camera: Camera) -> np.ndarray | None:
        """(6, 6) covariance of a successful fix (module docstring), None if it has no usable std."""
        cfg = self.config
        std = float(est.position_std_m)
        if not np.isfinite(std):
            return None
        scale = cfg.fix_std_scale if int(est.num_inliers_3d) >= cfg.min_inliers_3d else cfg.fix_std_scale_2d
        pos = max(scale * std, cfg.min_fix_std_m)
        n = max(int(est.num_inliers) + int(est.num_inliers_3d), 1)
        f = float(np.mean(camera.focal))
        rot = np.sqrt((cfg.pixel_std / f) ** 2 / n + self._map_rotation_std**2)
        rot = max(rot, np.radians(cfg.min_rotation_std_deg))
        return np.diag([rot**2] * 3 + [pos**2] * 3)

    def _fixes(self, features: Features, camera: Camera, gravity: np.ndarray | None,
               prediction: Prediction) -> FixOutcome:
        """Stages 3-4: a fix from the map images near a usable prediction, else (or when it is
        rejected or fails) from global retrieval; the first that passes the gate is accepted."""
        near = self.references_near(prediction.pose, prediction.position_std_m) if prediction.usable else None
        attempts = ([near] if near is not None else []) + [None]  # None: global retrieval
        out = FixOutcome()
        for references in attempts:
            out.global_retrieval |= references is None
            est = self._fix(features, camera, references, gravity)
            out.last = est
            cov = self.fix_covariance(est, camera) if est.success and est.pose is not None else None
            if cov is None:
                out.status = "failed"
                continue
            if prediction.pose is None:
                out.accepted, out.status = (est.pose, cov), "accepted"
                break
            out.mahalanobis_sq = mahalanobis_sq(est.pose, cov, prediction.pose, prediction.covariance)
            if out.mahalanobis_sq <= self._gate:
                out.accepted, out.status = (est.pose, cov), "accepted"
                break
            out.status = "rejected"
            out.rejected.append(FixAttempt(est, cov, references is None, out.mahalanobis_sq))
        return out

    def _reject_visual_odometry(self, prediction: Prediction, fixes: FixOutcome, stamp: float) -> Prediction:
        """Visual odometry can be wrong (few matches, bas-relief ambiguity). When two fixes
        (local and global retrieval) agree with each other and with the weak motion model, the
        visual factor is the outlier: it is replaced and the fix accepted (``fixes`` updated)."""
        if fixes.accepted is not None or prediction.motion.source != "visual" or len(fixes.rejected) < 2:
            return prediction
        a, b = fixes.rejected[:2]
        if mahalanobis_sq(a.pose, a.covariance, b.pose, b.covariance) > self._gate:
            return prediction
        weak = self._constant_motion(self._dt(stamp))
        n = len(self._poses) - 1
        alt = weak.cur_from_prev @ self._poses[n - 1]
        alt_rel = RelativeFactor(n - 1, n, weak.cur_from_prev, weak.covariance)
        alt_cov = marginal_covariances(self._poses[:-1] + [alt], self._absolute, self._relative[:-1] + [alt_rel])[-1]
        d2 = mahalanobis_sq(b.pose, b.covariance, alt, alt_cov)
        if d2 > self._gate:
            return prediction
        self._poses[-1], self._relative[-1] = alt, alt_rel
        fixes.accepted, fixes.status, fixes.mahalanobis_sq, fixes.rejected = (b.pose, b.covariance), "accepted", d2, []
        replaced = Motion(prediction.motion.cur_from_prev, prediction.motion.covariance, "visual_rejected",
                          prediction.motion.model)
        return Prediction(alt, alt_cov, replaced, prediction.position_std_m, prediction.usable)

    def _track_kidnap(self, fixes: FixOutcome) -> None:
        """Rejected global fixes that agree with each other (through the motion between them) over
        consecutive frames confirm a kidnap."""
        if fixes.accepted is not None:
            return
        for attempt in fixes.rejected:
            if attempt.global_retrieval:
                self._consider_kidnap(attempt.pose, attempt.covariance)

    def _consider_kidnap(self, pose: Pose, cov: np.ndarray) -> None:
        c = self._candidate
        if c is not None:
            predicted = c.cur_from_cand @ c.pose
            motion_world = c.motion_cov.copy()
            R = c.pose.R.T
            motion_world[3:, 3:] = R @ c.motion_cov[3:, 3:] @ R.T
            if mahalanobis_sq(pose, cov, predicted, c.covariance + motion_world) <= self._gate:
                self._candidate = _Candidate(pose, cov, c.count + 1)
                return
        self._candidate = _Candidate(pose, cov, 1)

    # ---- the graph ------------------------------------------------------------------------
    def _solve(self) -> None:
        sol = solve_pose_graph(self._poses, self._absolute, self._relative)
        self._poses = sol.poses
        self._cov = sol.covariances[-1]
        self._trim()
        self._update_speed()

    def _update_speed(self) -> None:
        """Speed (scale of visual odometry) from the raw fixes, not the fused poses: fused poses
        follow visual odometry, whose scale comes from this speed (a feedback loop that would
        keep any initial error). Chord between the oldest and newest of the last
        ``SPEED_FIXES`` fixes: longer baselines dilute the fixes' noise."""
        fixes = self._fix_centers[-SPEED_FIXES:]
        if len(fixes) >= 2 and fixes[-1][0] > fixes[0][0]:
            self._speed = float(np.linalg.norm(fixes[-1][1] - fixes[0][1])) / (fixes[-1][0] - fixes[0][0])

    def _trim(self) -> None:
        """Marginalise the oldest nodes beyond the window."""
        while len(self._poses) > self.config.window:
            absolute, relative = marginalize_first(self._poses, self._absolute, self._relative)
            if not absolute:  # nothing anchored the oldest node: keep the current marginal as a prior
                cov = marginal_covariances(self._poses, self._absolute, self._relative)[1]
                absolute = [AbsoluteFactor(0, self._poses[1], cov)]
            self._absolute, self._relative = absolute, relative
            self._poses, self._stamps, self._localized = self._poses[1:], self._stamps[1:], self._localized[1:]

    def _initialize(self, pose: Pose, cov: np.ndarray, stamp: float) -> None:
        self._poses, self._stamps, self._localized = [pose], [stamp], [True]
        self._absolute, self._relative = [AbsoluteFactor(0, pose, cov)], []
        self._fix_centers = [(stamp, pose.center)]
        self._cov = cov
        self._candidate = None

    def _fuse(self, prediction: Prediction, fixes: FixOutcome, stamp: float) -> tuple[FrameStatus, bool]:
        """Stages 5-6: add the accepted fix and solve the window, re-initialise on a confirmed
        kidnap, or keep the prediction. Returns the frame's status and whether it re-initialised."""
        cfg = self.config
        if fixes.accepted is not None:
            if prediction.pose is None:
                self._initialize(*fixes.accepted, stamp)
            else:
                self._absolute.append(AbsoluteFactor(len(self._poses) - 1, *fixes.accepted))
                self._localized[-1] = True
                self._fix_centers.append((stamp, fixes.accepted[0].center))
                self._solve()
            self._candidate = None
            return FrameStatus.LOCALIZED, False
        if self._candidate is not None and self._candidate.count >= cfg.kidnap_confirmations:
            self._initialize(self._candidate.pose, self._candidate.covariance, stamp)
            logger.info("stream re-initialised at t=%.3f from %d consistent global fixes", stamp,
                        cfg.kidnap_confirmations)
            fixes.status = "accepted"
            return FrameStatus.LOCALIZED, True
        if prediction.pose is not None:
            self._cov = prediction.covariance
            self._trim()
        # One contradicting fix is not enough to doubt the prediction (kidnap_suspected says it),
        # but with no measured motion (the stream jumped: no visual-odometry matches) and a
        # contradicting global fix, the prediction is not a pose to act on.
        doubt = prediction.motion.source == "constant" and any(a.global_retrieval for a in fixes.rejected)
        return (FrameStatus.PREDICTED if prediction.usable and not doubt else FrameStatus.LOST), False

    # ---- one frame ------------------------------------------------------------------------
    def step(self, image: ImageSource, camera: Camera | None, stamp: float, odometry: Pose | None = None,
             gravity: object | None = None) -> SequenceEstimate:
        """Localize the next frame of the stream.

        Args:
            image: (H, W) grayscale or (H, W, 3) BGR uint8 image (or JPEG/PNG bytes, or a file).
            camera: its intrinsics; None: the map's (when the map has exactly one camera).
            stamp: time in seconds (increasing; used to scale visual odometry by speed).
            odometry: this frame's ``cam_from_odom`` pose from wheel odometry (any fixed
                odometry frame; only differences between frames are used), or None.
            gravity: (3,) gravity direction (down) in the camera frame, or None (mounted like the
                map cameras); passed to the single-frame fixes.

        Returns:
            :class:`SequenceEstimate` — every frame gets one.

        Raises:
            InputError: a bad image, camera (e.g. of another size than the image), gravity,
                odometry or stamp; the stream is unchanged.
        """
        if odometry is not None and not isinstance(odometry, Pose):
            raise InputError(f"odometry: expected a planarloc Pose (cam_from_odom) or None, "
                             f"got {type(odometry).__name__}")
        stamp = float(stamp)
        if not np.isfinite(stamp):
            raise InputError(f"stamp: expected a finite time in seconds, got {stamp}")
        t0 = time.perf_counter()
        query = self.localizer.prepare(image, camera, gravity=gravity)
        return self.step_query(query, stamp, odometry, t0)

    def step_query(self, query: Query, stamp: float, odometry: Pose | None = None,
                   started: float | None = None) -> SequenceEstimate:
        """Localize the next frame, prepared with :meth:`Localizer.prepare` (see :meth:`step`)."""
        t0 = time.perf_counter() if started is None else started
        features = extract_features(query.image, self.localizer.features)
        prediction = self._predict(features, query.camera, stamp, odometry)
        self._carry_candidate(prediction.motion, stamp)
        fixes = self._fixes(features, query.camera, query.gravity, prediction)
        prediction = self._reject_visual_odometry(prediction, fixes, stamp)
        self._track_kidnap(fixes)
        status, reinitialized = self._fuse(prediction, fixes, stamp)
        self._prev = (features, query.camera, stamp, odometry)
        pose = self._poses[-1] if self._poses else None
        cov = self._cov if pose is not None else np.full((6, 6), np.inf)
        pos_std, rot_std = _stds(cov)
        if status != FrameStatus.LOST and pos_std > self.config.lost_std_m:
            status = FrameStatus.LOST   # never report a pose as usable beyond lost_std_m
        return SequenceEstimate(
            stamp=stamp, status=status.value, pose=pose, covariance=cov, position_std_m=pos_std,
            rotation_std_deg=rot_std, fix=fixes.last, fix_status=fixes.status,
            rejected=[a.report() for a in fixes.rejected], mahalanobis_sq=fixes.mahalanobis_sq,
            motion_source=prediction.motion.source, motion_model=prediction.motion.model,
            global_retrieval=fixes.global_retrieval, kidnap_suspected=self._candidate is not None,
            reinitialized=reinitialized, seconds=time.perf_counter() - t0)
