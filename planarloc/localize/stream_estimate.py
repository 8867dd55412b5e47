"""What a stream gives back: one :class:`SequenceEstimate` per frame (the frame record), its
:class:`FrameStatus`, and the stream's counters (:class:`StreamStats`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.robust.result import PoseEstimate


class FrameStatus(str, Enum):
    """``localized``: an absolute pose supports the frame at its own time; ``predicted``: a
    usable pose carried by the motion model; ``lost``: no usable pose."""

    LOCALIZED = "localized"
    PREDICTED = "predicted"
    LOST = "lost"


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
        message: why a frame is ``lost`` when the frame itself is the reason (a blank frame),
            else empty.
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
    message: str = ""

    @property
    def success(self) -> bool:
        """A pose the caller may use: ``localized`` or ``predicted``."""
        return self.pose is not None and self.status != FrameStatus.LOST.value


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
    fix_waits: int = 0  # frames that waited for a fix more than ``max_fix_lag_s`` behind
    fix_cpu_s: float = 0.0
    point_fixes: int = 0
    point_fixes_rejected: int = 0
    reinitializations: int = 0
    blank: int = 0  # blank frames (not tracked, not fixed; status lost)

    def count_fix(self, status: str) -> None:
        name = f"fixes_{status}"
        if hasattr(self, name):
            setattr(self, name, getattr(self, name) + 1)
