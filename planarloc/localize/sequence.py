"""Localize a camera stream at camera rate: frame-to-frame tracking on the frame path, absolute
fixes off it, fused into a sliding-window pose graph when they arrive.

:class:`SequenceLocalizer` takes one frame at a time (:meth:`SequenceLocalizer.step`) and
returns a :class:`SequenceEstimate` for every frame: a pose, its (6, 6) covariance and a status —

- ``localized``: the pose is anchored by an accepted absolute fix in the window, the motion
  since that fix was measured (wheel or visual odometry), at most ``MAX_VISUAL_FRAMES`` visual
  motions since the last absolute factor (a fix or the tracked map points), the latest fix
  result was an acceptance, and its position std is at most ``SequenceConfig.localized_std_m``
  (0.3 m, as a single fix's ``max_position_std_m``);
- ``predicted``: a usable pose (position std at most ``SequenceConfig.lost_std_m``) that is not
  ``localized`` (the latest fix failed or was rejected, a constant-velocity guess since the last
  fix, or no fix left in the window);
- ``lost``: no pose yet, a pose too uncertain to use, or a prediction without measured motion
  that a global fix contradicts (the stream jumped).

A single contradicting fix does not make a frame ``lost`` (the frame says ``kidnap_suspected``):
one wrong fix is more likely than a kidnap.

**The frame path** (every frame; ~45 ms of CPU at 1241×376, :mod:`planarloc.localize.tracking`):

1. **Motion** from the previous frame: wheel odometry when given (``odometry`` = ``cam_from_odom``
   pose of this frame in the odometry frame, e.g. a TUM pose file), otherwise visual odometry:
   corners of the previous frame tracked by pyramidal Lucas-Kanade, the relative pose of the
   tracks (planar 2-point solver, 6DoF when the planar model does not fit). Visual odometry has
   no scale: its translation is scaled by the speed measured over the accepted fixes (a line
   through their speeds, so that an accelerating robot is not extrapolated too slow); when a
   later fix changes that speed, the window's visual motions are scaled again. Without either,
   a constant-velocity guess with a large covariance.
2. **Prediction**: the new node of the window.
3. **Fusion** of the fix results that have arrived: each refers to an older frame; it is added at
   that frame's node and the window is solved again, which re-predicts the current node.
4. **Tracked map points**: an accepted fix (and the global fix a confirmed kidnap restarts from)
   also brings the 3D points of its inlier keypoints
   (the map's local structure, else triangulated with the map image), tracked on to the current
   frame; every frame then gets a pose from them (PnP), an absolute factor whose std grows with
   the frames they were tracked through. This is what keeps the position metric between fixes.
5. **A fix job** for this frame when the fix worker is idle (and ``fix_every`` frames have
   passed).

**Fixes** (:mod:`planarloc.localize.fixes`; ~100 ms of CPU at 1241×376: SIFT on the frame at half
resolution, matching and the single-frame estimator): against the map images nearest to the frame's prediction, else global retrieval,
gated by the χ²(6) Mahalanobis test against the frame's prediction. With
``SequenceConfig.fixes = "background"`` (default) they run in a worker thread and the frame path
never waits for them, except for the first frame (and until a first fix is accepted): there is
nothing to track from; and a frame that doubts its pose (a rejected global fix after a motion
that was not measured: a suspected kidnap, the frame is ``lost``) waits for the fix in flight: it
has no pose to give early, and waiting confirms the kidnap within a few frames instead of at the
rate the worker gets CPU next to the frame path. With ``"wait"`` they run inside :meth:`SequenceLocalizer.step`,
deterministically: a job every ``fix_every`` frames whose result is fused ``fix_delay`` frames
later (``fix_every=1, fix_delay=0``: every frame waits for its own fix, the per-frame design).

**Checks on fix results** (at the fix's node):

- If the motion into that node came from visual odometry and two fixes (local and global)
  agree with each other and with a constant-velocity model, the visual-odometry factor is the
  outlier and is replaced.
- ``kidnap_confirmations`` consecutive rejected global fixes that agree with each other (through
  the motion between them) re-initialise the window at the latest of them. The first of them
  is carried along the window when its node is marginalised (fixes far apart still confirm
  each other), and while a kidnap is suspected fix jobs go to global retrieval at once (the
  map images near the doubted prediction are the wrong place to look).

**Counted, never silent** (:attr:`SequenceLocalizer.stats` and per frame): a frame whose latency
(arrival → pose) exceeds ``max_latency_s`` is ``late``; frames missing from the stream (a gap of
more than 1.5 frame periods between stamps) are ``missing_frames``; fix results for frames that
already left the window are ``stale``.

Covariances: :attr:`SequenceEstimate.covariance` is in ROS order (``world_from_camera``: centre
x y z in the map's world, then a rotation vector about the world axes), like
:attr:`planarloc.robust.result.PoseEstimate.covariance`; :func:`ros_covariance` converts the pose
graph's ``(rotation, centre)`` order to it (docs/conventions.md, "Pose covariances").
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array
from planarloc.localize.fixes import (
    BackgroundFixes,
    FixAttempt,
    FixJob,
    FixOutcome,
    FixResult,
    FixSolver,
    ImmediateFixes,
    mahalanobis_sq,
)
from planarloc.localize.localizer import Localizer
from planarloc.localize.query import ImageSource, Query
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.tracking import (
    MIN_POINTS,
    FrameHistory,
    FrameTracker,
    Tracked,
    direction_basis,
    pose_from_points,
)
from planarloc.robust.pose_graph import (
    AbsoluteFactor,
    RelativeFactor,
    marginal_covariances,
    marginalize_first,
    so3_log,
    solve_pose_graph,
)
from planarloc.robust.result import PoseEstimate

logger = logging.getLogger(__name__)

#: visual-odometry speed: from this many of the latest fixes (see ``_update_speed``)
SPEED_FIXES = 4
#: the speed model's acceleration is at most this (m/s²), and applied at most this far from its data (s)
MAX_ACCELERATION, MAX_EXTRAPOLATION_S = 5.0, 1.0
#: motions that count as measured (a pose after them may be ``localized``)
MEASURED = ("odometry", "visual")
#: a pose chained by visual odometry through more frames than this since the last node with an
#: absolute factor (a fix or tracked map points) is not ``localized``: a wrong basin of 2D-2D
#: motion explains the tracks as well as the truth and its covariance cannot say so (on the
#: generated office world at 320x240, 4 in 39 motions are 5-15° off in rotation)
MAX_VISUAL_FRAMES = 2
#: a pose from fewer tracked points than this has its std scaled by sqrt(this / inliers)
POINT_FIX_FULL_SUPPORT = 60
#: recent frame periods used to tell missing frames
PERIODS_KEPT = 9


class _SingleThreadBlas:
    """Holds the BLAS library to one thread while any stream that asked for it is open.

    OpenBLAS threads spin while they wait for work: on a 2-core machine they take the cores the
    frame path and the fix worker need (``kitti_seq2``, frame path only: 131 ms of CPU per frame
    with numpy's default threads, 44 ms with one; the pose graph's small products and inverses
    gain nothing from threads). The limit is process-wide (``threadpoolctl``); the last stream
    to close restores the earlier setting.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._limit: object | None = None

    def hold(self) -> None:
        with self._lock:
            if self._users == 0:
                from threadpoolctl import threadpool_limits

                self._limit = threadpool_limits(limits=1, user_api="blas")
            self._users += 1

    def release(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0 and self._limit is not None:
                self._limit.restore_original_limits()  # type: ignore[attr-defined]
                self._limit = None


_BLAS = _SingleThreadBlas()


class FrameStatus(str, Enum):
    LOCALIZED = "localized"
    PREDICTED = "predicted"
    LOST = "lost"


def ros_covariance(cam_from_world: Pose, covariance: np.ndarray) -> np.ndarray:
    """The pose graph's (6, 6) covariance of a ``cam_from_world`` pose in ROS order.

    Pose-graph order ``(ω, δc)``: ``R_cw' = exp([ω]×) R_cw`` (a rotation of the camera frame),
    ``c' = c + δc`` (the centre in the world, metres). ROS order (``PoseWithCovariance``, and
    :attr:`PoseEstimate.covariance`): ``(δc, φ)`` of ``world_from_camera`` with
    ``R_wc' = exp([φ]×) R_wc``, a rotation vector about the world axes. ``φ = −R_cwᵀ ω``.

    Args:
        cam_from_world: the pose the covariance belongs to.
        covariance: (6, 6) in pose-graph order; a non-finite one stays all inf.

    Returns:
        (6, 6) in ROS order.

    Example:
        >>> C = np.diag([1e-4] * 3 + [0.01] * 3)     # 0.57° per axis, 0.1 m per axis
        >>> np.diag(ros_covariance(Pose.identity(), C)).tolist()
        [0.01, 0.01, 0.01, 0.0001, 0.0001, 0.0001]
    """
    C = check_array("covariance", covariance, (6, 6), finite=False)
    if not np.all(np.isfinite(C)):
        return np.full((6, 6), np.inf)
    J = np.zeros((6, 6))
    J[:3, 3:] = np.eye(3)
    J[3:, :3] = -cam_from_world.R.T
    out = J @ C @ J.T
    return 0.5 * (out + out.T)


def graph_covariance(cam_from_world: Pose, covariance: np.ndarray) -> np.ndarray:
    """The inverse of :func:`ros_covariance`: ROS order to pose-graph order ``(ω, δc)``."""
    C = check_array("covariance", covariance, (6, 6), finite=False)
    if not np.all(np.isfinite(C)):
        return np.full((6, 6), np.inf)
    J = np.zeros((6, 6))
    J[:3, 3:] = -cam_from_world.R
    J[3:, :3] = np.eye(3)
    out = J @ C @ J.T
    return 0.5 * (out + out.T)


@dataclass
class SequenceEstimate:
    """What :meth:`SequenceLocalizer.step` returns for one frame (the stream's frame record).

    Attributes:
        stamp: the frame's time in seconds.
        status: ``"localized"``, ``"predicted"`` or ``"lost"`` (:class:`FrameStatus`).
        pose: ``cam_from_world`` (the fused pose, or the prediction); None only while no fix
            was ever accepted.
        covariance: (6, 6) in ROS order: ``world_from_camera``'s centre (x, y, z in the map's
            world, metres), then its rotation vector about the world axes (radians); all inf
            without a pose. :func:`ros_covariance`.
        position_std_m: sqrt of the largest eigenvalue of the position block (inf: no pose).
        rotation_std_deg: the same for rotation, in degrees.
        fix: the absolute estimate whose result was handled in this step (of this frame or,
            with background fixes, of an earlier one: ``fix_stamp``), or None.
        fix_status: of that result: ``"accepted"``, ``"rejected"`` (failed the gate),
            ``"failed"`` (the single-frame estimator failed), ``"stale"`` (its frame had left the
            window); else ``"pending"`` (a fix is being computed) or ``"none"``.
        fix_stamp: the stamp of the frame that fix belongs to (None without one).
        rejected: one dict per rejected fix: centre, Mahalanobis distance², retrieval kind.
        mahalanobis_sq: distance² of the accepted or last rejected fix to its prediction.
        motion_source: ``"odometry"``, ``"visual"``, ``"constant"``, ``"none"`` (first frame) or
            ``"visual_rejected"`` (visual odometry contradicted an accepted fix and was replaced
            by the constant-velocity model).
        motion_model: ``"planar"`` / ``"6dof"`` for visual odometry, else empty.
        tracks: corners tracked from the previous frame (visual odometry).
        global_retrieval: whether the handled fix used global (VLAD) retrieval.
        kidnap_suspected: a rejected fix is waiting for confirmation.
        reinitialized: the window was reset from global localization in this step.
        seconds: wall time of the step.
        latency_s: from the frame's arrival (``step(..., arrival=)``, default the call) to its pose.
        late: ``latency_s`` exceeded ``SequenceConfig.max_latency_s``.
        missing_frames: frames missing before this one, judged from the gap since the previous
            stamp (more than 1.5 times the recent median frame period).
        cpu_s: CPU time of the step in the calling thread (``time.thread_time``; a fix computed
            in the step included, a background one not).
        graph_covariance: (6, 6) covariance in the pose graph's order ``(rotation, centre)``
            (docs/conventions.md, "Pose covariances").
    """

    stamp: float
    status: str
    pose: Pose | None
    covariance: np.ndarray
    position_std_m: float
    rotation_std_deg: float
    fix: PoseEstimate | None = None
    fix_status: str = "none"
    fix_stamp: float | None = None
    rejected: list[dict] = field(default_factory=list)
    mahalanobis_sq: float = float("nan")
    motion_source: str = "none"
    motion_model: str = ""
    tracks: int = 0
    global_retrieval: bool = False
    kidnap_suspected: bool = False
    reinitialized: bool = False
    seconds: float = 0.0
    latency_s: float = 0.0
    late: bool = False
    missing_frames: int = 0
    cpu_s: float = 0.0
    graph_covariance: np.ndarray | None = None

    @property
    def success(self) -> bool:
        """A pose the caller may use: ``localized`` or ``predicted``."""
        return self.pose is not None and self.status != FrameStatus.LOST.value

    def to_dict(self) -> dict:
        """The JSON record: every attribute but ``graph_covariance``; a pose as ``quat_wxyz``
        and ``t`` of ``cam_from_world`` with ``covariance_xyz_rotvec`` (ROS order, as a
        single fix's record)."""
        d = {
            "stamp": self.stamp, "success": self.success, "status": self.status,
            "position_std_m": _finite_or_none(self.position_std_m),
            "rotation_std_deg": _finite_or_none(self.rotation_std_deg),
            "fix_status": self.fix_status, "fix_stamp": self.fix_stamp, "rejected": self.rejected,
            "mahalanobis_sq": _finite_or_none(self.mahalanobis_sq),
            "motion_source": self.motion_source, "motion_model": self.motion_model, "tracks": self.tracks,
            "global_retrieval": self.global_retrieval, "kidnap_suspected": self.kidnap_suspected,
            "reinitialized": self.reinitialized, "seconds": self.seconds, "latency_s": self.latency_s,
            "late": self.late, "missing_frames": self.missing_frames, "cpu_s": self.cpu_s,
            "fix": None if self.fix is None else self.fix.to_dict(),
        }
        if self.pose is not None:
            d["quat_wxyz"] = [float(v) for v in self.pose.quat_wxyz]
            d["t"] = [float(v) for v in self.pose.t]
            d["covariance_xyz_rotvec"] = np.where(np.isfinite(self.covariance), self.covariance, None).tolist()
        return d


@dataclass
class StreamStats:
    """Counters of a stream since the last :meth:`SequenceLocalizer.reset`."""

    frames: int = 0
    late: int = 0
    missing: int = 0
    fixes_submitted: int = 0
    fixes_accepted: int = 0
    fixes_rejected: int = 0
    fixes_failed: int = 0
    fixes_stale: int = 0
    fix_waits: int = 0           # frames that waited for a fix more than ``max_fix_lag_s`` behind
    fix_cpu_s: float = 0.0
    point_fixes: int = 0
    point_fixes_rejected: int = 0
    reinitializations: int = 0

    def count_fix(self, status: str) -> None:
        name = f"fixes_{status}"
        if hasattr(self, name):
            setattr(self, name, getattr(self, name) + 1)


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _stds(cov: np.ndarray) -> tuple[float, float]:
    """(position std [m], rotation std [deg]) of a pose-graph covariance: worst axes."""
    if not np.all(np.isfinite(cov)):
        return float("inf"), float("inf")
    rot = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0)))
    pos = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
    return pos, float(np.degrees(rot))


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
    """A rejected global fix waiting for confirmation, at the node of frame ``stamp``."""

    pose: Pose
    covariance: np.ndarray
    count: int
    stamp: float


@dataclass(frozen=True)
class Motion:
    """The motion since the previous frame, ``cur_from_prev``, with its (6, 6) covariance.

    ``source``: ``"odometry"``, ``"visual"``, ``"constant"``, ``"none"`` (first frame) or
    ``"visual_rejected"``; ``model``: ``"planar"`` / ``"6dof"`` for visual odometry, else empty.
    ``unscaled``: visual odometry scaled by the speed: its rotation, unit direction, stamp, time
    step and (5, 5) covariance (or None), to scale it again when the speed estimate changes.
    """

    cur_from_prev: Pose
    covariance: np.ndarray
    source: str
    model: str = ""
    unscaled: tuple | None = None


@dataclass
class _Handled:
    """What the fix results handled in one step say (for the frame's record)."""

    result: FixResult | None = None
    status: str = "none"
    reinitialized: bool = False


class SequenceLocalizer:
    """Localizes an ordered camera stream against a map, one frame per :meth:`step`.

    The public API (used by the CLI, the service's fleet sessions and the ROS 2 node): the
    constructor, :meth:`step` (or :meth:`step_query` for a prepared query), :meth:`reset`,
    :meth:`close` (or ``with``), :attr:`stats`, and the returned :class:`SequenceEstimate`
    (:meth:`SequenceEstimate.to_dict` is the frame record).

    Args:
        localizer: a single-frame :class:`Localizer` (its config sets method and structure).
            Background fixes open their own on the same map file.
        config: :class:`SequenceConfig`.

    Example:
        >>> with SequenceLocalizer(Localizer("kitti.db")) as seq:             # doctest: +SKIP
        ...     for image, stamp in stream:
        ...         est = seq.step(image, camera, stamp)
        ...         print(est.status, est.pose.center if est.pose else None, est.position_std_m)
        >>> offline = SequenceLocalizer(loc, SequenceConfig(fixes="wait"))    # doctest: +SKIP
    """

    def __init__(self, localizer: Localizer, config: SequenceConfig | None = None) -> None:
        if not isinstance(localizer, Localizer):
            raise InputError(f"localizer: expected a planarloc Localizer, got {type(localizer).__name__}")
        if config is not None and not isinstance(config, SequenceConfig):
            raise InputError(f"config: expected a SequenceConfig, got {type(config).__name__}")
        self.localizer = localizer
        self.config = config or SequenceConfig()
        self._blas = self.config.single_thread_blas
        if self._blas:
            _BLAS.hold()
        self._solver = FixSolver(localizer, self.config)
        self._gate = self._solver.gate
        self._tracker = FrameTracker(self.config.tracker)
        self._history = FrameHistory(self.config.window + 1)
        self._fixes: ImmediateFixes | BackgroundFixes = (
            ImmediateFixes(self._solver, self.config.fix_delay, self._history, self.config.tracker)
            if self.config.fixes == "wait" else
            BackgroundFixes(localizer, self.config, self._history, self.config.tracker))
        self._generation = 0
        self.reset()

    # ---- life cycle -----------------------------------------------------------------------
    def warm_up(self) -> float:
        """Pay before the first frame for what a process's first queries cost (~1 s: compiled
        kernels loaded, the map images' pair matches; :meth:`Localizer.warm_up`), in the calling
        thread and, with background fixes, in the fix worker (which starts on it when the
        stream opens); returns the seconds it took. Front doors that take live frames call it
        before their first one; without it the first frames wait (or are dropped) instead."""
        t0 = time.perf_counter()
        self.localizer.warm_up()
        if isinstance(self._fixes, BackgroundFixes):
            self._fixes.wait_warm()
        return time.perf_counter() - t0

    def reset(self) -> None:
        """Forget the stream (e.g. before a new sequence); fixes still in flight are ignored."""
        self._generation += 1
        self._fixes.discard()
        self._tracker.reset()
        self._history.clear()
        self._dirty = False
        self._poses: list[Pose] = []
        self._stamps: list[float] = []
        self._localized: list[bool] = []
        self._sources: list[str] = []
        self._unscaled: list[tuple | None] = []
        self._absolute: list[AbsoluteFactor] = []
        self._relative: list[RelativeFactor] = []
        self._cov = np.full((6, 6), np.inf)
        self._cov_exact = True
        self._prev: tuple[float, Pose | None] | None = None   # stamp, odometry of the previous frame
        self._periods: deque[float] = deque(maxlen=PERIODS_KEPT)
        self._speed: float | None = None
        self._speed_model: tuple[float, float, float] | None = None   # (t_ref, speed at t_ref, acceleration)
        self._candidate: _Candidate | None = None
        self._fix_centers: list[tuple[float, np.ndarray]] = []
        self._latest_fix = "none"
        self._doubt = False
        self._frame = 0
        self._last_job: int | None = None
        self._last_job_stamp = float("-inf")
        self.stats = StreamStats()

    def close(self) -> None:
        """Stop the fix worker (background fixes) and release the BLAS limit; the object is not
        used afterwards."""
        self._fixes.close()
        if self._blas:
            self._blas = False
            _BLAS.release()

    def __enter__(self) -> SequenceLocalizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- fixes (delegated) ----------------------------------------------------------------
    def references_near(self, pose: Pose, position_std_m: float) -> list[str] | None:
        """The ``local_top_n`` map images nearest to ``pose`` (distance plus 1 m per 30° of
        viewing-direction difference); None when fewer than 2 qualify (use global retrieval)."""
        return self._solver.references_near(pose, position_std_m)

    def fix_covariance(self, est: PoseEstimate, camera: Camera) -> np.ndarray | None:
        """(6, 6) pose-graph covariance of a successful fix (:mod:`planarloc.localize.fixes`)."""
        return self._solver.fix_covariance(est, camera)

    # ---- motion ---------------------------------------------------------------------------
    def _motion(self, tracked: Tracked, stamp: float, odometry: Pose | None) -> Motion:
        """The motion since the previous frame (odometry, else visual odometry, else constant velocity)."""
        cfg = self.config
        prev_stamp, prev_odometry = self._prev  # type: ignore[misc]
        dt = stamp - prev_stamp
        if odometry is not None and prev_odometry is not None:
            motion = odometry @ prev_odometry.inverse()
            d = motion.inverse().t
            dist = float(np.linalg.norm(d))
            angle = float(np.linalg.norm(so3_log(motion.R[None])[0]))
            along = cfg.odometry_translation_std * dist + cfg.odometry_min_std_m
            rot = cfg.odometry_rotation_std * angle + np.radians(cfg.odometry_min_rotation_std_deg)
            return Motion(motion, _motion_covariance(d, along, along, rot), "odometry")
        vo = tracked.relative
        if vo is not None and vo.success and vo.pose is not None:
            # u: the direction of the centre of cur in prev's frame
            return self._visual(vo.pose.R, vo.pose.inverse().t, stamp, dt, vo.model, tracked.covariance)
        return self._constant_motion(len(self._poses) - 1, dt)

    def _visual(self, R: np.ndarray, u: np.ndarray, stamp: float, dt: float, model: str,
                cov5: np.ndarray | None) -> Motion:
        """Visual odometry ``(R, u)`` over the ``dt`` seconds up to ``stamp``, scaled by the speed
        then (``unscaled`` keeps it for a later speed model); without a speed, a weak length.

        Covariance over (rotation, centre displacement ``d = dist · u``): the tracks' own
        (5, 5) covariance of rotation and direction (:func:`~planarloc.localize.tracking.
        relative_pose_covariance`, with their correlation), plus ``vo_rotation_std_deg`` and
        ``vo_direction_std_deg`` per axis and 2 cm across, and the speed's uncertainty along."""
        cfg = self.config
        speed = self._speed_at(stamp - dt / 2)
        if speed is None:
            dist, along = 0.0, cfg.max_speed_mps * dt
        else:
            dist = speed * dt
            scale_std = cfg.vo_scale_std if self._speed_model is not None else cfg.vo_first_scale_std
            along = scale_std * dist + 0.05
        across = dist * np.radians(cfg.vo_direction_std_deg) + 0.02
        cov = _motion_covariance(u, along, across, np.radians(cfg.vo_rotation_std_deg))
        if cov5 is not None:
            B = direction_basis(u) * dist
            cov[:3, :3] += cov5[:3, :3]
            cov[:3, 3:] += cov5[:3, 3:] @ B.T
            cov[3:, :3] += B @ cov5[3:, :3]
            cov[3:, 3:] += B @ cov5[3:, 3:] @ B.T
        return Motion(Pose(R, -R @ (u * dist)), cov, "visual", model, (R, u, stamp, dt, cov5))

    def _constant_motion(self, last: int, dt: float) -> Motion:
        """Constant velocity from nodes ``last − 1`` and ``last``, with a large covariance (a weak
        motion model: position std ``max_speed_mps · dt / 5`` plus half the step, rotation 20°);
        before a speed is measured, no motion with std ``max_speed_mps · dt`` (as :meth:`_visual`)."""
        motion, d = Pose.identity(), np.zeros(3)
        if last >= 1 and self._speed is not None:
            step = self._poses[last] @ self._poses[last - 1].inverse()
            d = step.inverse().t
            n = np.linalg.norm(d)
            if n > 1e-9:
                d = d / n * self._speed * dt
            motion = Pose(step.R, -step.R @ d)
        known = last >= 1 and self._speed is not None
        along = 0.5 * float(np.linalg.norm(d)) + (0.2 if known else 1.0) * self.config.max_speed_mps * dt
        return Motion(motion, _motion_covariance(d, along, along, np.radians(20.0)), "constant")

    def _add_node(self, motion: Motion, stamp: float) -> None:
        """The new node predicted by ``motion`` from the last one, and its marginal covariance."""
        n = len(self._poses)
        self._poses.append(motion.cur_from_prev @ self._poses[-1])
        self._stamps.append(stamp)
        self._localized.append(False)
        self._sources.append(motion.source)
        self._unscaled.append(motion.unscaled)
        self._relative.append(RelativeFactor(n - 1, n, motion.cur_from_prev, motion.covariance))
        # Until the window is solved or marginalised again (once per frame, :meth:`_refresh`): the
        # last covariance grown by the motion's, without cross terms (for gating only).
        cov = self._cov.copy()
        R = self._poses[-2].R.T
        cov[:3, :3] += motion.covariance[:3, :3]
        cov[3:, 3:] += R @ motion.covariance[3:, 3:] @ R.T
        self._cov, self._cov_exact = cov, False
        self._trim()

    # ---- the graph ------------------------------------------------------------------------
    def _solve(self) -> None:
        """Solve the window if a factor was added since the last solve."""
        if not self._dirty:
            return
        if self._update_speed():
            self._rescale_visual()
        sol = solve_pose_graph(self._poses, self._absolute, self._relative)
        self._poses = sol.poses
        self._cov, self._cov_exact = sol.covariances[-1], True
        self._dirty = False
        if self._speed is None and self._update_speed(solved=True):   # a first speed from the solved poses
            self._rescale_visual()
            sol = solve_pose_graph(self._poses, self._absolute, self._relative)
            self._poses, self._cov = sol.poses, sol.covariances[-1]

    def _refresh(self) -> None:
        """Solve the window if a factor was added, else marginalise it if a node was: the
        current node's covariance is exact afterwards."""
        if self._dirty:
            self._solve()
        elif not self._cov_exact and self._poses:
            self._cov, self._cov_exact = marginal_covariances(self._poses, self._absolute, self._relative)[-1], True

    def _update_speed(self, solved: bool = False) -> bool:
        """Speed (scale of visual odometry) from the raw fixes, not the fused poses: fused poses
        follow visual odometry, whose scale comes from this speed (a feedback loop that would
        keep any initial error). Each pair of consecutive fixes among the last ``SPEED_FIXES``
        gives a speed (distance over time) at its mid time; a line through them (weighted by
        their durations, acceleration at most ``MAX_ACCELERATION``) gives the speed at any time
        (:meth:`_speed_at`): a car that accelerates would otherwise be extrapolated too slow.
        Before a second fix, the two latest nodes with an absolute factor (the first fix and
        the poses from its tracked world points) give a first speed, once ``solved``. Returns
        whether the speed changed."""
        fixes = sorted(self._fix_centers, key=lambda f: f[0])[-SPEED_FIXES:]
        seg = [((a[0] + b[0]) / 2, float(np.linalg.norm(b[1] - a[1])) / (b[0] - a[0]), b[0] - a[0])
               for a, b in zip(fixes, fixes[1:]) if b[0] > a[0]]
        if not seg:
            anchored = sorted({f.node for f in self._absolute})[-2:]
            if not solved or self._speed_model is not None or len(anchored) < 2:
                return False
            a, b = anchored
            dt = self._stamps[b] - self._stamps[a]
            old, self._speed = self._speed, float(np.linalg.norm(self._poses[b].center - self._poses[a].center)) / dt
            return old is None
        t, v, w = (np.array(x) for x in zip(*seg))
        t_ref = float(t[-1])
        v_ref, accel = float(np.average(v, weights=w)), 0.0
        if len(seg) >= 3:
            A = np.stack([np.ones_like(t), t - t_ref], axis=1) * np.sqrt(w)[:, None]
            v_ref, accel = (float(x) for x in np.linalg.lstsq(A, v * np.sqrt(w), rcond=None)[0])
            accel = float(np.clip(accel, -MAX_ACCELERATION, MAX_ACCELERATION))
            v_ref = float(np.average(v - accel * (t - t_ref), weights=w))
        old, self._speed_model = self._speed_model, (t_ref, max(v_ref, 0.0), accel)
        self._speed = self._speed_at(self._stamps[-1] if self._stamps else t_ref)
        return old != self._speed_model

    def _speed_at(self, stamp: float) -> float | None:
        """The speed at ``stamp`` (:meth:`_update_speed`), else the last one measured."""
        if self._speed_model is None:
            return self._speed
        t_ref, v, accel = self._speed_model
        return max(v + accel * float(np.clip(stamp - t_ref, -MAX_EXTRAPOLATION_S, MAX_EXTRAPOLATION_S)), 0.0)

    def _rescale_visual(self) -> None:
        """Scale the window's speed-scaled visual odometry by the current speed: a speed found
        wrong by a later fix would otherwise stay in the motions measured with it."""
        for k, f in enumerate(self._relative):
            raw = self._unscaled[f.j] if f.j == f.i + 1 and self._sources[f.j] == "visual" else None
            if raw is not None:
                R, u, stamp, dt, cov5 = raw
                m = self._visual(R, u, stamp, dt, "", cov5)
                self._relative[k] = RelativeFactor(f.i, f.j, m.cur_from_prev, m.covariance)

    def _trim(self) -> None:
        """Marginalise the oldest nodes beyond the window (a kidnap candidate at the oldest node
        is carried to the next one)."""
        while len(self._poses) > self.config.window:
            c = self._candidate
            if c is not None and c.stamp == self._stamps[0]:
                # a kidnap candidate outlives its node: the next fix result may come after it left
                self._candidate = _Candidate(*self._carried(c.pose, c.covariance, 0, 1), c.count, self._stamps[1])
            absolute, relative = marginalize_first(self._poses, self._absolute, self._relative)
            if not absolute:  # nothing anchored the oldest node: keep the current marginal as a prior
                cov = marginal_covariances(self._poses, self._absolute, self._relative)[1]
                absolute = [AbsoluteFactor(0, self._poses[1], cov)]
            self._absolute, self._relative = absolute, relative
            for name in ("_poses", "_stamps", "_localized", "_sources", "_unscaled"):
                setattr(self, name, getattr(self, name)[1:])

    def _initialize(self, pose: Pose, cov: np.ndarray, stamp: float) -> None:
        self._poses, self._stamps, self._localized, self._sources = [pose], [stamp], [True], ["none"]
        self._unscaled = [None]
        self._absolute, self._relative = [AbsoluteFactor(0, pose, cov)], []
        self._fix_centers = [(stamp, pose.center)]
        self._cov, self._cov_exact = cov, True
        self._candidate = None
        self._doubt = False

    def _reinitialize(self, node: int, pose: Pose, cov: np.ndarray) -> None:
        """Restart the window at ``node`` from ``pose`` (a confirmed kidnap), keeping the
        motions measured since."""
        stamps, sources = self._stamps[node:], ["none"] + self._sources[node + 1:]
        unscaled = [None] + self._unscaled[node + 1:]
        relative = [RelativeFactor(f.i - node, f.j - node, f.j_from_i, f.covariance)
                    for f in self._relative if f.i >= node]
        self._initialize(pose, cov, stamps[0])
        self._speed_model = None   # the last speed stays a guess until two fixes measure it again
        self._stamps, self._sources, self._unscaled = stamps, sources, unscaled
        self._localized = [True] + [False] * (len(stamps) - 1)
        self._relative = relative
        self._rescale_visual()     # with the guessed speed's larger std
        self._poses += [Pose.identity()] * len(relative)
        self._rechain(0)
        self._dirty = bool(relative)
        self._tracker.set_points(None)
        self.stats.reinitializations += 1

    def _rechain(self, start: int) -> None:
        """Initial guesses of the nodes after ``start`` from their motions (before a solve)."""
        for f in sorted(self._relative, key=lambda f: f.j):
            if f.j > start and f.j == f.i + 1:
                self._poses[f.j] = f.j_from_i @ self._poses[f.i]

    # ---- fix results ----------------------------------------------------------------------
    def _node(self, stamp: float) -> int | None:
        for k in range(len(self._stamps) - 1, -1, -1):
            if self._stamps[k] == stamp:
                return k
        return None

    def _handle(self, result: FixResult, handled: _Handled) -> None:
        """Fuse one fix result at its frame's node (stale if that node left the window)."""
        if result.generation != self._generation:
            return
        out = result.outcome
        handled.result = result
        self.stats.fix_cpu_s += result.cpu_s
        if not self._poses:          # the stream starts: the result belongs to the current frame
            if out.accepted is not None:
                self._initialize(*out.accepted, result.stamp)
            handled.status = out.status
            self._latest_fix = out.status
            self.stats.count_fix(out.status)
            return
        node = self._node(result.stamp)
        if node is None:
            handled.status = "stale"
            self.stats.fixes_stale += 1
            logger.debug("fix of t=%.3f arrived after its frame left the window", result.stamp)
            return
        if out.accepted is None:
            self._reject_visual_odometry(node, out)
        if out.accepted is not None:
            self._absolute.append(AbsoluteFactor(node, *out.accepted))
            self._localized[node] = True
            self._fix_centers.append((result.stamp, out.accepted[0].center))
            self._dirty = True
            self._candidate = None
            self._doubt = False
            if result.points is not None:
                self._tracker.set_points(result.tracked_to(self._history, self.config.tracker).points)
        else:
            self._track_kidnap(node, out, handled)
            if handled.reinitialized and result.points is not None:   # the points of the fix restarted from
                self._tracker.set_points(result.tracked_to(self._history, self.config.tracker).points)
        handled.status = out.status
        self._latest_fix = "accepted" if handled.reinitialized else out.status
        self.stats.count_fix(out.status)

    def _reject_visual_odometry(self, node: int, fixes: FixOutcome) -> None:
        """Visual odometry can be wrong (few tracks, bas-relief ambiguity). When two fixes
        (local and global retrieval) agree with each other and with the weak motion model, the
        visual factor into ``node`` is the outlier: it is replaced and the fix accepted
        (``fixes`` updated)."""
        if node < 1 or self._sources[node] != "visual" or len(fixes.rejected) < 2:
            return
        a, b = fixes.rejected[:2]
        if mahalanobis_sq(a.pose, a.covariance, b.pose, b.covariance) > self._gate:
            return
        k = next(i for i, f in enumerate(self._relative) if f.j == node and f.i == node - 1)
        weak = self._constant_motion(node - 1, self._stamps[node] - self._stamps[node - 1])
        relative = list(self._relative)
        relative[k] = RelativeFactor(node - 1, node, weak.cur_from_prev, weak.covariance)
        poses = list(self._poses)
        poses[node] = weak.cur_from_prev @ poses[node - 1]
        alt_cov = marginal_covariances(poses, self._absolute, relative)[node]
        d2 = mahalanobis_sq(b.pose, b.covariance, poses[node], alt_cov)
        if d2 > self._gate:
            return
        self._poses, self._relative = poses, relative
        self._sources[node], self._unscaled[node] = "visual_rejected", None
        self._rechain(node)
        fixes.accepted, fixes.status, fixes.mahalanobis_sq, fixes.rejected = (b.pose, b.covariance), "accepted", d2, []

    def _track_kidnap(self, node: int, fixes: FixOutcome, handled: _Handled) -> None:
        """Rejected global fixes that agree with each other (through the motion between them)
        over consecutive fix results confirm a kidnap; with no measured motion since the last
        fix, one rejected global fix already makes the stream doubt its pose."""
        anchor = max((k for k, loc in enumerate(self._localized) if loc), default=-1)
        for attempt in fixes.rejected:
            if not attempt.global_retrieval:
                continue
            if any(s not in MEASURED for s in self._sources[anchor + 1:node + 1]):
                self._doubt = True
            self._consider_kidnap(node, attempt)
        c = self._candidate
        if c is not None and c.count >= self.config.kidnap_confirmations:
            self._reinitialize(node, c.pose, c.covariance)
            logger.info("stream re-initialised at t=%.3f from %d consistent global fixes", c.stamp,
                        self.config.kidnap_confirmations)
            fixes.status = "accepted"
            handled.reinitialized = True

    def _carried(self, pose: Pose, cov: np.ndarray, prev: int, node: int) -> tuple[Pose, np.ndarray]:
        """A pose estimate of node ``prev`` moved to node ``node`` through the window's motion
        between them, its covariance grown by those motions' (and, where the motion was not
        wheel odometry, by the weak constant-velocity model's: visual odometry may be wrong
        exactly across a kidnap, so agreeing fixes then need only agree within that model)."""
        moved = (self._poses[node] @ self._poses[prev].inverse()) @ pose
        motion_cov = np.zeros((6, 6))
        for f in self._relative:
            if prev < f.j <= node:
                motion_cov += f.covariance
                if self._sources[f.j] != "odometry":
                    dt = self._stamps[f.j] - self._stamps[f.i]
                    motion_cov += self._constant_motion(f.i, dt).covariance
        R = pose.R.T
        motion_cov[3:, 3:] = R @ motion_cov[3:, 3:] @ R.T
        return moved, cov + motion_cov

    def _consider_kidnap(self, node: int, attempt: FixAttempt) -> None:
        c = self._candidate
        prev = self._node(c.stamp) if c is not None else None
        if c is not None and prev is not None and prev < node:
            predicted, cov = self._carried(c.pose, c.covariance, prev, node)
            if mahalanobis_sq(attempt.pose, attempt.covariance, predicted, cov) <= self._gate:
                self._candidate = _Candidate(attempt.pose, attempt.covariance, c.count + 1, self._stamps[node])
                return
        self._candidate = _Candidate(attempt.pose, attempt.covariance, 1, self._stamps[node])

    def _replace_visual(self, pose: Pose, cov: np.ndarray) -> bool:
        """The current node's pose from its tracked map points contradicts a prediction made
        with visual odometry: when it agrees with the constant-velocity model instead, the
        visual factor is the outlier (2D-2D motion has wrong basins that explain the tracks as
        well as the truth: a small step next to a turn) and is replaced. Returns whether it was."""
        n = len(self._poses) - 1
        if n < 1 or self._sources[n] != "visual":
            return False
        weak = self._constant_motion(n - 1, self._stamps[n] - self._stamps[n - 1])
        relative = [f if f.j != n else RelativeFactor(n - 1, n, weak.cur_from_prev, weak.covariance)
                    for f in self._relative]
        poses = self._poses[:-1] + [weak.cur_from_prev @ self._poses[n - 1]]
        alt_cov = marginal_covariances(poses, self._absolute, relative)[n]
        if not mahalanobis_sq(pose, cov, poses[n], alt_cov) <= self._gate:
            return False
        self._poses, self._relative, self._cov = poses, relative, alt_cov
        self._sources[n], self._unscaled[n] = "visual_rejected", None
        return True

    def _point_fix(self, stamp: float, camera: Camera) -> None:
        """The current node's pose from the world points tracked into this frame
        (:func:`~planarloc.localize.tracking.pose_from_points`), gated by χ²(6) against the
        prediction; a contradicting one drops the points."""
        cfg = self.config
        points = self._tracker.points
        if points is None or points.stamp != stamp or len(points) < MIN_POINTS:
            return
        prior = self._poses[-1]
        fit = pose_from_points(prior, points.points, camera.cam_from_img(points.pixels.astype(float)),
                               float(np.mean(camera.focal)))
        if fit is None:
            return
        grow = (1.0 + cfg.point_fix_std_per_frame * points.hops) * np.sqrt(max(1.0, POINT_FIX_FULL_SUPPORT / fit[1]))
        cov = np.diag([np.radians(cfg.point_fix_rotation_std_deg * grow) ** 2] * 3
                      + [(cfg.point_fix_min_std_m * grow) ** 2] * 3)
        if not mahalanobis_sq(fit[0], cov, prior, self._cov) <= self._gate and not self._replace_visual(fit[0], cov):
            self._tracker.set_points(None)
            self.stats.point_fixes_rejected += 1
            return
        self._absolute.append(AbsoluteFactor(len(self._poses) - 1, fit[0], cov))
        self._dirty = True
        self.stats.point_fixes += 1

    # ---- one frame ------------------------------------------------------------------------
    def _check_frame(self, stamp: object, odometry: object) -> float:
        if odometry is not None and not isinstance(odometry, Pose):
            raise InputError(f"odometry: expected a planarloc Pose (cam_from_odom) or None, "
                             f"got {type(odometry).__name__}")
        try:
            t = float(stamp)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise InputError(f"stamp: expected a time in seconds, got {stamp!r}") from None
        if not np.isfinite(t):
            raise InputError(f"stamp: expected a finite time in seconds, got {t}")
        if self._prev is not None and t <= self._prev[0]:
            what = "the same as" if t == self._prev[0] else "before"
            raise InputError(f"stamp {t:.6f}: {what} the previous frame's {self._prev[0]:.6f}; frames must come in "
                             "time order, each once (reset() starts a new stream)")
        return t

    def _missing(self, stamp: float) -> int:
        if self._prev is None:
            return 0
        dt = stamp - self._prev[0]
        period = float(np.median(self._periods)) if len(self._periods) >= 3 else None
        self._periods.append(dt)
        if period is None or dt <= 1.5 * period:
            return 0
        return max(int(round(dt / period)) - 1, 1)

    def _job(self, query: Query, stamp: float) -> FixJob:
        if not self._poses:
            return FixJob(stamp, query.image, query.camera, query.gravity, None, False, float("inf"), self._generation)
        std, _ = _stds(self._cov)
        # a suspected kidnap: the map images near the prediction are the wrong place to look
        usable = std <= self.config.lost_std_m and self._candidate is None and not self._doubt
        return FixJob(stamp, query.image, query.camera, query.gravity, (self._poses[-1], self._cov),
                      usable, std, self._generation)

    def step(self, image: ImageSource, camera: Camera | None, stamp: float, odometry: Pose | None = None,
             gravity: object | None = None, arrival: float | None = None) -> SequenceEstimate:
        """Localize the next frame of the stream.

        Args:
            image: (H, W) grayscale or (H, W, 3) BGR uint8 image (or JPEG/PNG bytes, or a file).
            camera: its intrinsics, of the image's size; None: the map's (when the map has
                exactly one camera).
            stamp: time in seconds, strictly increasing along the stream (a frame given twice or
                out of order is an error); it scales visual odometry by speed.
            odometry: this frame's ``cam_from_odom`` pose from wheel odometry (any fixed
                odometry frame; only differences between frames are used), or None.
            gravity: (3,) gravity direction (down) in the camera frame, or None (mounted like the
                map cameras); passed to the single-frame fixes.
            arrival: ``time.perf_counter()`` when the frame arrived (default: now), for
                ``latency_s`` and ``late``.

        Returns:
            :class:`SequenceEstimate` — every frame gets one.

        Raises:
            InputError: a bad image, camera (e.g. of another size than the image), gravity,
                odometry or stamp; the stream is unchanged.
        """
        t0 = time.perf_counter() if arrival is None else float(arrival)
        self._check_frame(stamp, odometry)
        query = self.localizer.prepare(image, camera, gravity=gravity)
        return self.step_query(query, stamp, odometry, t0)

    def step_query(self, query: Query, stamp: float, odometry: Pose | None = None,
                   started: float | None = None) -> SequenceEstimate:
        """Localize the next frame, prepared with :meth:`Localizer.prepare` (see :meth:`step`;
        ``started`` is its ``arrival``)."""
        t_call, cpu0 = time.perf_counter(), time.thread_time()
        t0 = t_call if started is None else started
        if not isinstance(query, Query):
            raise InputError(f"query: expected a prepared planarloc Query, got {type(query).__name__}")
        stamp = self._check_frame(stamp, odometry)
        missing = self._missing(stamp)
        handled = _Handled()
        frame = self._frame
        prev_odometry = self._prev[1] if self._prev is not None else None
        self._history.append(stamp, query.image)
        tracked = self._tracker.track(query.image, query.camera, stamp,
                                      estimate_motion=bool(self._poses) and (odometry is None or prev_odometry is None))
        motion = Motion(Pose.identity(), np.zeros((6, 6)), "none")
        if not self._poses:
            # Nothing to track from: this frame waits for its fix.
            result = self._fixes.solve_now(self._job(query, stamp))
            self.stats.fixes_submitted += 1
            self._last_job, self._last_job_stamp = frame, stamp
            self._handle(result, handled)
            if self._poses:
                self._tracker.set_points(result.points)
        else:
            motion = self._motion(tracked, stamp, odometry)
            self._add_node(motion, stamp)
            for result in self._fixes.collect(frame):
                self._handle(result, handled)
            self._point_fix(stamp, query.camera)
            self._refresh()
            due = self._last_job is None or frame - self._last_job >= self.config.fix_every
            if due and not self._fixes.busy:
                self._fixes.submit(self._job(query, stamp), frame)
                self.stats.fixes_submitted += 1
                self._last_job, self._last_job_stamp = frame, stamp
            lagging = (self.config.fixes == "background" and self._fixes.busy
                       and stamp - self._last_job_stamp > self.config.max_fix_lag_s)
            if lagging:   # frames faster than the fixes: bound how far odometry chains from the last one
                self.stats.fix_waits += 1
            for result in self._fixes.collect(frame, wait=lagging):
                self._handle(result, handled)
            self._refresh()
            if self.config.fixes == "background" and self._fixes.busy and self._doubt:
                # A suspected kidnap (the frame is lost): nothing to give it either, it waits for the
                # fix in flight, so that the kidnap is confirmed in a few frames, not at the rate the
                # worker gets CPU. (Not for frames lost by a grown std: on a loaded machine waiting
                # drops frames, whose gaps make visual odometry fail, which makes the std grow.)
                for result in self._fixes.collect(frame, wait=True):
                    self._handle(result, handled)
                self._refresh()
        self._prev = (stamp, odometry)
        self._frame += 1
        return self._report(stamp, motion, tracked, handled, missing, t_call, t0, cpu0)

    def _status(self) -> FrameStatus:
        pos_std, _ = _stds(self._cov)
        if not self._poses or pos_std > self.config.lost_std_m or self._doubt:
            return FrameStatus.LOST  # never report a pose as usable beyond lost_std_m
        anchor = max((k for k, loc in enumerate(self._localized) if loc), default=None)
        measured = max((f.node for f in self._absolute), default=-1)
        visual = sum(s == "visual" for s in self._sources[measured + 1:])
        if (anchor is not None and self._latest_fix == "accepted" and pos_std <= self.config.localized_std_m
                and all(s in MEASURED for s in self._sources[anchor + 1:]) and visual <= MAX_VISUAL_FRAMES):
            return FrameStatus.LOCALIZED
        return FrameStatus.PREDICTED

    def _report(self, stamp: float, motion: Motion, tracked: Tracked, handled: _Handled, missing: int,
                t_call: float, t0: float, cpu0: float) -> SequenceEstimate:
        pose = self._poses[-1] if self._poses else None
        cov = self._cov if pose is not None else np.full((6, 6), np.inf)
        pos_std, rot_std = _stds(cov)
        status = self._status()
        out = handled.result.outcome if handled.result is not None else FixOutcome()
        fix_status = handled.status
        if handled.result is None:
            fix_status = "pending" if self._fixes.busy else "none"
        source = motion.source
        if self._sources and self._stamps[-1] == stamp and self._sources[-1] == "visual_rejected":
            source = self._sources[-1]            # a fix replaced this frame's visual motion
        now = time.perf_counter()
        latency = now - t0
        late = latency > self.config.max_latency_s
        self.stats.frames += 1
        self.stats.late += int(late)
        self.stats.missing += missing
        return SequenceEstimate(
            stamp=stamp, status=status.value, pose=pose,
            covariance=ros_covariance(pose, cov) if pose is not None else np.full((6, 6), np.inf),
            position_std_m=pos_std, rotation_std_deg=rot_std, fix=out.last, fix_status=fix_status,
            fix_stamp=None if handled.result is None else handled.result.stamp,
            rejected=[a.report() for a in out.rejected], mahalanobis_sq=out.mahalanobis_sq,
            motion_source=source, motion_model=motion.model, tracks=tracked.tracks,
            global_retrieval=out.global_retrieval, kidnap_suspected=self._candidate is not None,
            reinitialized=handled.reinitialized, seconds=now - t_call, latency_s=latency, late=late,
            missing_frames=missing, cpu_s=time.thread_time() - cpu0, graph_covariance=cov.copy())
