"""Fix fusion for the stream: what an absolute fix result, accepted or rejected, and the map
points tracked into a frame do to the pose window, the motion model and the kidnap monitor.

:class:`FixFusion` holds no state of its own beyond the latest fix status: it acts on the
:class:`~planarloc.localize.pose_window.PoseWindow`, :class:`~planarloc.localize.motion_model.MotionModel`,
:class:`~planarloc.localize.kidnap.KidnapMonitor` and tracker that
:class:`~planarloc.localize.sequence.SequenceLocalizer` owns, and counts into its
:class:`~planarloc.localize.stream_estimate.StreamStats`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.localize.fixes import FixAttempt, FixOutcome, FixResult, mahalanobis_sq
from planarloc.localize.kidnap import KidnapCandidate, KidnapMonitor
from planarloc.localize.motion_model import Motion, MotionModel
from planarloc.localize.pose_window import PoseWindow
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.stream_estimate import StreamStats
from planarloc.localize.tracking import (
    MIN_POINTS,
    FrameHistory,
    FrameTracker,
    pose_from_points,
    tracked_points_covariance,
)

logger = logging.getLogger(__name__)

#: motions that count as measured (a pose after them may be ``localized``)
MEASURED = ("odometry", "visual")


def _rejected_covariance(attempt: FixAttempt) -> np.ndarray:
    """The covariance of a rejected fix: only fixes with one are gated, hence rejected."""
    if attempt.covariance is None:
        raise ValueError("a rejected fix without a covariance")
    return attempt.covariance


@dataclass
class HandledFixes:
    """What the fix results handled in one step say (for the frame's record)."""

    result: FixResult | None = None
    status: str = "none"
    reinitialized: bool = False


class FixFusion:
    """Fuses fix results and tracked map points into the stream's pose window.

    Args:
        config: the stream's :class:`SequenceConfig`.
        gate: the χ²(6) gate on a fix's Mahalanobis distance to the prediction.
        window, motion, kidnap, tracker, history: the stream's own (shared, not copied).
    """

    def __init__(
        self,
        config: SequenceConfig,
        gate: float,
        window: PoseWindow,
        motion: MotionModel,
        kidnap: KidnapMonitor,
        tracker: FrameTracker,
        history: FrameHistory,
    ) -> None:
        self.config = config
        self._gate = gate
        self._window = window
        self._motion = motion
        self._kidnap = kidnap
        self._tracker = tracker
        self._history = history
        self.reset(StreamStats())

    def reset(self, stats: StreamStats) -> None:
        """A new stream, counted into ``stats``."""
        self.stats = stats
        #: the status of the latest fix result ("none" before the first)
        self.latest_fix = "none"

    def weak(self, last: int, dt: float) -> Motion:
        """The constant-velocity motion from node ``last`` over ``dt`` seconds."""
        return self._motion.constant(self._window.last_step(last), dt)

    def weak_covariance(self, last: int, dt: float) -> np.ndarray:
        return self.weak(last, dt).covariance

    def start(self, pose: Pose, cov: np.ndarray, stamp: float) -> None:
        self._window.start(pose, cov, stamp)
        self._motion.restart(stamp, pose.center, keep_speed=True)
        self._kidnap.clear()

    def restart_at(self, node: int, pose: Pose, cov: np.ndarray) -> None:
        """Restart the window at ``node`` from ``pose`` (a confirmed kidnap), keeping the
        motions measured since; the last speed stays a guess until two fixes measure it again."""
        w = self._window
        stamp = w.nodes[node].stamp
        w.restart_at(node, pose, cov)
        self._motion.restart(stamp, pose.center, keep_speed=True)
        self._kidnap.clear()
        w.rescale(self._motion.visual)  # with the guessed speed's larger std
        w.rechain(0)
        self._tracker.set_points(None)
        self.stats.reinitializations += 1

    def handle(self, result: FixResult, handled: HandledFixes) -> None:
        """Fuse one fix result (of the current stream) at its frame's node (stale if that node left
        the window)."""
        out = result.outcome
        handled.result = result
        self.stats.fix_cpu_s += result.cpu_s
        w = self._window
        if not len(w):  # the stream starts: the result belongs to the current frame
            if out.accepted is not None:
                pose, cov = out.accepted
                self.start(pose, cov, result.stamp)
            self._count_fix(out.status, handled)
            return
        node = w.node_at(result.stamp)
        if node is None:
            handled.status = "stale"
            self.stats.fixes_stale += 1
            logger.debug("fix of t=%.3f arrived after its frame left the window", result.stamp)
            return
        if out.accepted is None:
            self._reject_visual_odometry(node, out)
        if out.accepted is not None:
            pose, cov = out.accepted
            self._observe_scale(node, pose, cov)
            w.add_absolute(node, pose, cov)
            w.nodes[node].fixed = True
            # the fix's own std (its covariance is scaled by fix_std_scale for the graph)
            std = float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])) / self.config.fix_std_scale
            self._motion.add_fix(result.stamp, pose.center, std)
            self._kidnap.accept(result.stamp)
            if result.points is not None:
                self._tracker.set_points(result.tracked_to(self._history, self.config.tracker).points)
        else:
            self._track_kidnap(node, out, handled)
            if handled.reinitialized and result.points is not None:  # the points of the fix restarted from
                self._tracker.set_points(result.tracked_to(self._history, self.config.tracker).points)
        self._count_fix(out.status, handled)
        if handled.reinitialized:
            self.latest_fix = "accepted"

    def _count_fix(self, status: str, handled: HandledFixes) -> None:
        handled.status = status
        self.latest_fix = status
        self.stats.count_fix(status)

    def _reject_visual_odometry(self, node: int, fixes: FixOutcome) -> None:
        """Two fixes (local, global) that agree with each other and with constant velocity but not
        with the visual motion into ``node``: that motion is replaced and the fix accepted."""
        w = self._window
        if node < 1 or w.nodes[node].source != "visual" or len(fixes.rejected) < 2:
            return
        a, b = fixes.rejected[:2]
        cov_a, cov_b = _rejected_covariance(a), _rejected_covariance(b)
        if mahalanobis_sq(a.pose, cov_a, b.pose, cov_b) > self._gate:
            return
        weak = self.weak(node - 1, w.nodes[node].stamp - w.nodes[node - 1].stamp)
        alt = w.with_motion(node, weak)
        d2 = mahalanobis_sq(b.pose, cov_b, alt.poses[node], alt.covariance)
        if d2 > self._gate:
            return
        w.adopt(alt, "visual_rejected")
        w.rechain(node)
        fixes.accepted, fixes.status, fixes.mahalanobis_sq, fixes.rejected = (
            (b.pose, cov_b),
            "accepted",
            d2,
            [],
        )

    def _track_kidnap(self, node: int, fixes: FixOutcome, handled: HandledFixes) -> None:
        """Rejected global fixes feed the kidnap monitor; a confirmed kidnap restarts the window."""
        w = self._window
        anchor = w.last_fixed()
        anchor = -1 if anchor is None else anchor
        for attempt in fixes.rejected:
            if not attempt.global_retrieval:
                continue
            if any(s not in MEASURED for s in w.sources_after(anchor)[: node - anchor]):
                self._kidnap.doubt = True
            self._kidnap.consider(
                attempt.pose,
                _rejected_covariance(attempt),
                w.nodes[node].stamp,
                lambda c: self._carry(c, node),
            )
        c = self._kidnap.confirmed()
        if c is not None:
            self.restart_at(node, c.pose, c.covariance)
            logger.info(
                "stream re-initialised at t=%.3f from %d consistent global fixes",
                c.stamp,
                self.config.kidnap_confirmations,
            )
            fixes.status = "accepted"
            handled.reinitialized = True

    def _carry(self, c: KidnapCandidate, node: int) -> tuple[Pose, np.ndarray] | None:
        prev = self._window.node_at(c.stamp)
        if prev is None or prev >= node:
            return None
        return self._window.carried(c.pose, c.covariance, prev, node, self.weak_covariance)

    def _observe_scale(self, node: int, pose: Pose, cov: np.ndarray) -> None:
        """An absolute pose at ``node`` against the visual steps since the previous one
        (:class:`~planarloc.localize.motion_model.ScaleDoubt`); a new doubt rescales them."""
        w = self._window
        prev = max((f.node for f in w.absolute if f.node < node), default=-1)
        if prev < 0 or any(n.source != "visual" for n in w.nodes[prev + 1 : node + 1]):
            return
        origin = w.nodes[prev].pose.center
        predicted = float(np.linalg.norm(w.nodes[node].pose.center - origin))
        measured = float(np.linalg.norm(pose.center - origin))
        std = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
        before = self._motion.doubt.std
        self._motion.doubt.observe(measured, predicted, 3.0 * std)
        if self._motion.doubt.std != before:
            w.rescale(self._motion.visual)
            w.marginalize()

    def _replace_visual(self, pose: Pose, cov: np.ndarray) -> bool:
        """A point fix that contradicts a visual-odometry prediction but agrees with constant
        velocity: the visual factor is the outlier (a wrong 2D-2D basin) and is replaced."""
        w = self._window
        n = len(w) - 1
        if n < 1 or w.nodes[n].source != "visual":
            return False
        alt = w.with_motion(n, self.weak(n - 1, w.nodes[n].stamp - w.nodes[n - 1].stamp))
        if not mahalanobis_sq(pose, cov, alt.poses[n], alt.covariance) <= self._gate:
            return False
        w.adopt(alt, "visual_rejected")
        return True

    def point_fix(self, stamp: float, camera: Camera) -> None:
        """The current node's pose from the map points tracked into this frame, gated by χ²(6)
        against the prediction; a contradicting one drops the points."""
        cfg = self.config
        points = self._tracker.points
        if points is None or points.stamp != stamp or len(points) < MIN_POINTS:
            return
        w = self._window
        rays, focal = camera.cam_from_img(points.pixels.astype(float)), float(np.mean(camera.focal))
        fit = pose_from_points(w.current.pose, points.points, rays, focal)
        if fit is None:
            return
        cov = tracked_points_covariance(
            fit[0],
            points.points,
            rays,
            focal,
            fit[1],
            points.hops,
            pixel_std=cfg.pixel_std,
            min_std_m=cfg.point_fix_min_std_m,
            rotation_std_deg=cfg.point_fix_rotation_std_deg,
            std_per_frame=cfg.point_fix_std_per_frame,
        )
        node = len(w) - 1
        self._observe_scale(node, fit[0], cov)
        if not mahalanobis_sq(
            fit[0], cov, w.current.pose, w.covariance
        ) <= self._gate and not self._replace_visual(fit[0], cov):
            self._tracker.set_points(None)
            self.stats.point_fixes_rejected += 1
            return
        w.add_absolute(node, fit[0], cov)
        self.stats.point_fixes += 1
