"""Localize a camera stream at camera rate: frame-to-frame tracking on the frame path, absolute
fixes off it, fused into a sliding-window pose graph when they arrive.

:class:`SequenceLocalizer` takes one frame at a time (:meth:`SequenceLocalizer.step`) and returns
a :class:`SequenceEstimate` for every frame: a pose, its (6, 6) covariance and a status —

- ``localized``: an absolute pose supports the frame **at its own time** (an accepted fix of this
  frame, or the map points tracked into it), the motion since the last accepted fix was measured
  (wheel or visual odometry), the latest fix result was an acceptance, and its position std is
  at most ``SequenceConfig.localized_std_m``;
- ``predicted``: a usable pose (position std at most ``SequenceConfig.max_pose_std_m``) carried by the
  motion model, with the uncertainty of what that model does not know
  (:mod:`planarloc.localize.motion_model`);
- ``lost``: no pose yet, a pose too uncertain to use, a frame that cannot be tracked (black,
  featureless), or a prediction a global fix contradicts with no measured motion to trust instead.

Every pose that leaves the stream, whatever its status, is a promise: it lies within
``3·position_std_m + 5 cm`` of the truth (``benchmarks/stream_trust.py`` checks it under dropped,
black and corrupt frames, stamps that lie, stop-and-go and kidnaps).

Who holds what: :class:`~planarloc.localize.pose_window.PoseWindow` the nodes, factors and
covariance (pose-graph order, :mod:`planarloc.geometry.pose_covariance`);
:class:`~planarloc.localize.motion_model.MotionModel` odometry, visual odometry and constant
velocity; :class:`~planarloc.localize.kidnap.KidnapMonitor` rejected global fixes that agree;
:class:`~planarloc.localize.fix_fusion.FixFusion` what a fix result or the tracked map points do
to them; :mod:`planarloc.localize.fixes` the absolute fixes, inside :meth:`SequenceLocalizer.step`
(``fixes="wait"``: deterministic) or in a worker thread (``"background"``, default: the frame path
waits only on its first frame, when it has no pose to give early, and more than ``max_fix_lag_s``
of stamps after the fix in flight); this module one step per frame and its report.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.pose_covariance import covariance_stds, graph_covariance, ros_covariance
from planarloc.geometry.validation import InputError
from planarloc.localize.fix_fusion import MEASURED, FixFusion, HandledFixes
from planarloc.localize.fixes import (
    BackgroundFixes,
    FixJob,
    FixOutcome,
    FixResult,
    FixSolver,
    ImmediateFixes,
)
from planarloc.localize.kidnap import KidnapMonitor
from planarloc.localize.localizer import Localizer
from planarloc.localize.motion_model import Motion, MotionModel, VisualStep
from planarloc.localize.pose_window import PoseWindow
from planarloc.localize.query import ImageSource, Query
from planarloc.localize.stream_clock import StreamClock
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.stream_estimate import FrameStatus, SequenceEstimate, StreamStats
from planarloc.localize.tracking import (
    FrameHistory,
    FrameTracker,
    Tracked,
    is_blank,
    view_broken,
)
from planarloc.numerics.blas_threads import BLAS_ONE_THREAD
from planarloc.robust.pose_graph import so3_log
from planarloc.robust.result import PoseEstimate

__all__ = [
    "FrameStatus",
    "SequenceConfig",
    "SequenceEstimate",
    "SequenceLocalizer",
    "StreamStats",
    "graph_covariance",
    "ros_covariance",
]

logger = logging.getLogger(__name__)

#: while the stamps are in doubt (:attr:`MotionModel.stamps_doubted`), a frame this many frames
#: after the fix in flight waits for it: visual odometry's length is then unknown to 100 %
DOUBTED_FIX_LAG_FRAMES = 2


class SequenceLocalizer:
    """Localizes an ordered camera stream against a map, one frame per :meth:`step`.

    The public API (used by the CLI, the service's fleet sessions and the ROS 2 node): the
    constructor, :meth:`step` (or :meth:`step_query` for a prepared query), :meth:`reset`,
    :meth:`close` (or ``with``), :attr:`stats`, and the returned :class:`SequenceEstimate`
    (:func:`planarloc.localize.records.frame_record` is its JSON record).

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
            BLAS_ONE_THREAD.hold()
        self._solver = FixSolver(localizer, self.config)
        self._gate = self._solver.gate
        self._tracker = FrameTracker(self.config.tracker)
        self._history = FrameHistory(self.config.window + 1)
        self._window = PoseWindow(self.config.window)
        self._clock = StreamClock()
        self._motion = MotionModel(self.config)
        self._kidnap = KidnapMonitor(self._gate, self.config.kidnap_confirmations)
        self._fixes: ImmediateFixes | BackgroundFixes = (
            ImmediateFixes(self._solver, self.config.fix_delay, self._history, self.config.tracker)
            if self.config.fixes == "wait"
            else BackgroundFixes(localizer, self.config, self._history, self.config.tracker)
        )
        self._fusion = FixFusion(
            self.config, self._gate, self._window, self._motion, self._kidnap, self._tracker, self._history
        )
        self._generation = 0
        self.reset()

    def warm_up(self) -> float:
        """Pay before the first frame for what a process's first queries cost (~1 s: compiled
        kernels loaded, the map images' pair matches; :meth:`Localizer.warm_up`), in the calling
        thread and, with background fixes, in the fix worker; returns the seconds it took."""
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
        self._window.clear()
        self._motion.reset()
        self._kidnap.clear()
        self._prev: tuple[float, Pose | None] | None = None  # stamp, odometry of the last tracked frame
        self._clock.reset()
        self._frame = 0
        self._last_job: int | None = None
        self._last_job_stamp = float("-inf")
        self.stats = StreamStats()
        self._fusion.reset(self.stats)

    def close(self) -> None:
        """Stop the fix worker (background fixes) and release the BLAS limit."""
        self._fixes.close()
        if self._blas:
            self._blas = False
            BLAS_ONE_THREAD.release()

    def __enter__(self) -> SequenceLocalizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def references_near(self, pose: Pose, position_std_m: float) -> list[str] | None:
        """The ``local_top_n`` map images nearest to ``pose``; None when fewer than 2 qualify."""
        return self._solver.references_near(pose, position_std_m)

    def fix_covariance(self, est: PoseEstimate, camera: Camera) -> np.ndarray | None:
        """(6, 6) pose-graph covariance of a successful fix (:mod:`planarloc.localize.fixes`)."""
        return self._solver.fix_covariance(est, camera)

    def _handle(self, result: FixResult, handled: HandledFixes) -> None:
        """Fuse one fix result (:class:`~planarloc.localize.fix_fusion.FixFusion`) unless it is of
        a stream before the last :meth:`reset`."""
        if result.generation == self._generation:
            self._fusion.handle(result, handled)

    def _frame_motion(self, tracked: Tracked, stamp: float, odometry: Pose | None) -> Motion:
        """The motion since the previous frame: odometry, else visual odometry, else constant velocity."""
        if self._prev is None:  # step() calls this only once a frame has been tracked
            raise RuntimeError("no previous frame to take the motion from")
        prev_stamp, prev_odometry = self._prev
        dt = stamp - prev_stamp
        if odometry is not None and prev_odometry is not None:
            return self._motion.odometry(odometry, prev_odometry)
        vo = tracked.relative
        weak = self._fusion.weak(len(self._window) - 1, dt)
        if vo is not None and vo.success and vo.pose is not None:
            since = (
                prev_stamp - self._window.anchor_stamp(len(self._window) - 1) if len(self._window) else 0.0
            )
            step = VisualStep(
                vo.pose.R, vo.pose.inverse().t, stamp, dt, tracked.covariance, since_anchor_s=since
            )
            return self._motion.disputed(self._motion.visual(step, vo.model), weak)
        return weak

    def _expected_turn_deg(self, odometry: Pose | None) -> float | None:
        """The rotation wheel odometry measured since the previous frame (degrees); None without."""
        if odometry is None or self._prev is None or self._prev[1] is None:
            return None
        return float(np.degrees(np.linalg.norm(so3_log((odometry @ self._prev[1].inverse()).R[None])[0])))

    def _solve(self) -> None:
        """Solve the window (after new factors), with the speed the fixes measure."""
        w = self._window
        if self._motion.update_speed(w.current.stamp):
            w.rescale(self._motion.visual)
        w.solve()
        if self._motion.speed is None:
            anchored = w.anchored_nodes()[-2:]
            if len(anchored) == 2:  # a first speed from the solved poses
                a, b = (w.nodes[k] for k in anchored)
                if self._motion.first_speed(
                    float(np.linalg.norm(b.pose.center - a.pose.center)), b.stamp - a.stamp
                ):
                    w.rescale(self._motion.visual)
                    w.solve()

    def _refresh(self) -> None:
        """Solve the window if a factor was added, else marginalise it if a node was: the
        current node's covariance is exact afterwards."""
        if self._window.dirty:
            self._solve()
        elif not self._window.exact:
            self._window.marginalize()

    def _trim(self) -> None:
        """Marginalise the oldest nodes beyond the window (a kidnap candidate at the oldest node
        is carried to the next one)."""
        w = self._window
        while len(w) > self.config.window:
            c = self._kidnap.candidate
            if c is not None and c.stamp == w.nodes[0].stamp:
                pose, cov = w.carried(c.pose, c.covariance, 0, 1, self._fusion.weak_covariance)
                self._kidnap.moved(c.stamp, pose, cov, w.nodes[1].stamp)
            w.drop_oldest()

    def _check_frame(self, stamp: object, odometry: object) -> float:
        if odometry is not None and not isinstance(odometry, Pose):
            raise InputError(
                f"odometry: expected a planarloc Pose (cam_from_odom) or None, got {type(odometry).__name__}"
            )
        return self._clock.check(stamp)

    def _job(self, query: Query, stamp: float) -> FixJob:
        w = self._window
        if not len(w):
            return FixJob(
                stamp, query.image, query.camera, query.gravity, None, False, float("inf"), self._generation
            )
        std, _ = covariance_stds(w.covariance)
        # a suspected kidnap: the map images near the prediction are the wrong place to look
        usable = std <= self.config.lost_std_m and not self._kidnap.suspected and not self._kidnap.doubted
        return FixJob(
            stamp,
            query.image,
            query.camera,
            query.gravity,
            (w.current.pose, w.covariance),
            usable,
            std,
            self._generation,
        )

    def step(
        self,
        image: ImageSource,
        camera: Camera | None,
        stamp: float,
        odometry: Pose | None = None,
        gravity: object | None = None,
        arrival: float | None = None,
    ) -> SequenceEstimate:
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

    def step_query(
        self, query: Query, stamp: float, odometry: Pose | None = None, started: float | None = None
    ) -> SequenceEstimate:
        """Localize the next frame, prepared with :meth:`Localizer.prepare` (see :meth:`step`;
        ``started`` is its ``arrival``)."""
        t_call, cpu0 = time.perf_counter(), time.thread_time()
        t0 = t_call if started is None else started
        if not isinstance(query, Query):
            raise InputError(f"query: expected a prepared planarloc Query, got {type(query).__name__}")
        stamp = self._check_frame(stamp, odometry)
        missing = self._clock.advance(stamp)
        if is_blank(query.image):
            return self._blank(stamp, missing, t_call, t0, cpu0)
        handled = HandledFixes()
        self._history.append(stamp, query.image)
        tracked = self._tracker.track(
            query.image, query.camera, stamp, estimate_motion=bool(len(self._window))
        )
        motion = Motion.none()
        if not len(self._window):
            self._first_fix(query, stamp, handled)
        else:
            motion = self._frame_motion(tracked, stamp, odometry)
            if view_broken(tracked, self.config.tracker.min_inliers, self._expected_turn_deg(odometry)):
                self._kidnap.broke_view(stamp)
            self._window.append(motion, stamp)
            self._trim()
            self._take_fixes(query, stamp, handled)
        self._prev = (stamp, odometry)
        self._frame += 1
        return self._report(stamp, motion, tracked, handled, missing, t_call, t0, cpu0)

    def _first_fix(self, query: Query, stamp: float, handled: HandledFixes) -> None:
        """Nothing to track from: this frame waits for its fix."""
        result = self._fixes.solve_now(self._job(query, stamp))
        self.stats.fixes_submitted += 1
        self._last_job, self._last_job_stamp = self._frame, stamp
        self._handle(result, handled)
        if len(self._window):
            self._tracker.set_points(result.points)

    def _take_fixes(self, query: Query, stamp: float, handled: HandledFixes) -> None:
        """Fuse the fix results that arrived and the tracked map points, submit this frame's fix
        job when the worker is idle; a frame too far ahead of the fix in flight, or with no pose
        to give early (doubted, a std beyond ``max_pose_std_m`` or ``lost_std_m``), waits for it."""
        frame = self._frame
        for result in self._fixes.collect(frame):
            self._handle(result, handled)
        self._fusion.point_fix(stamp, query.camera)
        self._refresh()
        due = self._last_job is None or frame - self._last_job >= self.config.fix_every
        if due and not self._fixes.busy:
            self._fixes.submit(self._job(query, stamp), frame)
            self.stats.fixes_submitted += 1
            self._last_job, self._last_job_stamp = frame, stamp
        background = self.config.fixes == "background"
        # frames faster than the fixes: bound how far odometry chains from the last one (in frames
        # when the stamp gaps have been seen to lie about time)
        behind = stamp - self._last_job_stamp > self.config.max_fix_lag_s or (
            self._motion.stamps_doubted
            and self._last_job is not None
            and frame - self._last_job >= DOUBTED_FIX_LAG_FRAMES
        )
        lagging = background and self._fixes.busy and behind
        if lagging:
            self.stats.fix_waits += 1
        for result in self._fixes.collect(frame, wait=lagging):
            self._handle(result, handled)
        self._refresh()
        lost = covariance_stds(self._window.covariance)[0] > min(
            self.config.lost_std_m, self.config.max_pose_std_m
        )
        if background and self._fixes.busy and (self._kidnap.doubted or lost):
            for result in self._fixes.collect(frame, wait=True):
                self._handle(result, handled)
            self._refresh()

    def _blank(self, stamp: float, missing: int, t_call: float, t0: float, cpu0: float) -> SequenceEstimate:
        """A blank frame (:func:`~planarloc.localize.tracking.is_blank`) is ``lost`` with a message,
        its pose the constant-velocity guess; it is not tracked, fixed or a node: the next frame
        is tracked from the last one with texture, like a dropped frame."""
        w = self._window
        pose, cov = None, np.full((6, 6), np.inf)
        if len(w):
            weak = self._fusion.weak(len(w) - 1, stamp - w.current.stamp)
            pose = weak.cur_from_prev @ w.current.pose
            R = w.current.pose.R.T
            cov = w.covariance.copy()
            cov[:3, :3] += weak.covariance[:3, :3]
            cov[3:, 3:] += R @ weak.covariance[3:, 3:] @ R.T
        self.stats.blank += 1
        self._frame += 1
        return self._estimate(
            stamp,
            FrameStatus.LOST,
            pose,
            cov,
            missing,
            (t_call, t0, cpu0),
            fix_status="pending" if self._fixes.busy else "none",
            motion_source="none" if pose is None else "constant",
            message="blank frame: no texture to track or localize (black, white or uniform); the stream "
            "goes on from the last frame with texture",
        )

    def _status(self) -> FrameStatus:
        w = self._window
        pos_std, _ = covariance_stds(w.covariance)
        usable_std = min(self.config.max_pose_std_m, self.config.lost_std_m)
        if not len(w) or pos_std > usable_std or self._kidnap.doubted:
            return FrameStatus.LOST  # never report a pose as usable beyond it
        anchor = w.last_fixed()
        current = len(w) - 1
        if (
            anchor is not None
            and self._fusion.latest_fix == "accepted"
            and pos_std <= self.config.localized_std_m
            and w.last_absolute() == current
            and all(s in MEASURED for s in w.sources_after(anchor))
        ):
            return FrameStatus.LOCALIZED
        return FrameStatus.PREDICTED

    def _report(
        self,
        stamp: float,
        motion: Motion,
        tracked: Tracked,
        handled: HandledFixes,
        missing: int,
        t_call: float,
        t0: float,
        cpu0: float,
    ) -> SequenceEstimate:
        w = self._window
        pose = w.current.pose if len(w) else None
        out = handled.result.outcome if handled.result is not None else FixOutcome()
        fix_status = handled.status
        if handled.result is None:
            fix_status = "pending" if self._fixes.busy else "none"
        source = motion.source
        if len(w) and w.current.stamp == stamp and w.current.source == "visual_rejected":
            source = w.current.source  # a fix replaced this frame's visual motion
        return self._estimate(
            stamp,
            self._status(),
            pose,
            w.covariance,
            missing,
            (t_call, t0, cpu0),
            fix=out.last,
            fix_status=fix_status,
            fix_stamp=None if handled.result is None else handled.result.stamp,
            rejected=[a.report() for a in out.rejected],
            mahalanobis_sq=out.mahalanobis_sq,
            motion_source=source,
            motion_model=motion.model,
            tracks=tracked.tracks,
            global_retrieval=out.global_retrieval,
            kidnap_suspected=self._kidnap.suspected,
            reinitialized=handled.reinitialized,
        )

    def _estimate(
        self,
        stamp: float,
        status: FrameStatus,
        pose: Pose | None,
        cov: np.ndarray,
        missing: int,
        times: tuple[float, float, float],
        **fields: Any,
    ) -> SequenceEstimate:
        """The frame's :class:`SequenceEstimate`, counted in :attr:`stats`; ``times``: the step's
        start, the frame's arrival and the thread's CPU time at the start."""
        t_call, t0, cpu0 = times
        if pose is None:
            cov = np.full((6, 6), np.inf)
        pos_std, rot_std = covariance_stds(cov)
        now = time.perf_counter()
        latency = now - t0
        late = latency > self.config.max_latency_s
        self.stats.frames += 1
        self.stats.late += int(late)
        self.stats.missing += missing
        return SequenceEstimate(
            stamp=stamp,
            status=status.value,
            pose=pose,
            covariance=ros_covariance(pose, cov) if pose is not None else np.full((6, 6), np.inf),
            position_std_m=pos_std,
            rotation_std_deg=rot_std,
            seconds=now - t_call,
            latency_s=latency,
            late=late,
            missing_frames=missing,
            cpu_s=time.thread_time() - cpu0,
            graph_covariance=cov.copy(),
            **fields,
        )
