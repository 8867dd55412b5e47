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
            "fix": None if self.fix is None else self.fix.to_dict(), "message": self.message,
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
    blank: int = 0               # blank frames (not tracked, not fixed; status lost)

    def count_fix(self, status: str) -> None:
        name = f"fixes_{status}"
        if hasattr(self, name):
            setattr(self, name, getattr(self, name) + 1)


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None

