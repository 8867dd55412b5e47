"""What the robust estimator returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.robust.status import Status


@dataclass
class RansacStatistics:
    """Counters of the hypothesis pipeline and time per stage (seconds).

    ``hypotheses`` counts solver outputs; each check counts the hypotheses it rejected:
    ``rejected_rcheck`` (eq. 12), ``rejected_pdcheck`` (ρ ≤ 0 or negative depth),
    ``rejected_consistency`` (direction mismatch), ``rejected_degenerate`` (a solver had no
    finite solution for the sample). ``scored`` = hypotheses that reached scoring. ``searches_skipped``:
    hypothesis families not searched because the planar pose passed every check (``auto`` and the planar
    methods' cross-check run the 6DoF search only when the planar answer is in doubt).
    ``time_s["total"]`` is the whole :func:`~planarloc.robust.absolute_pose.estimate_absolute_pose`
    call; the stages may overlap (``structure`` is part of ``setup``), so they need not add up to it.
    """

    iterations: int = 0
    hypotheses: int = 0
    rejected_rcheck: int = 0
    rejected_pdcheck: int = 0
    rejected_consistency: int = 0
    rejected_degenerate: int = 0
    scored: int = 0
    local_optimizations: int = 0
    searches_skipped: int = 0
    time_s: dict[str, float] = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float) -> None:
        self.time_s[stage] = self.time_s.get(stage, 0.0) + seconds

    def merge(self, other: RansacStatistics) -> None:
        """Add another search's counters and times to these."""
        for name, value in vars(other).items():
            if name == "time_s":
                for stage, seconds in value.items():
                    self.add_time(stage, seconds)
            else:
                setattr(self, name, getattr(self, name) + value)


@dataclass
class PoseEstimate:
    """Result of :func:`planarloc.estimate_absolute_pose`.

    Attributes:
        pose: the query ``cam_from_world``, or None when not ``success``.
        success: True only for a pose that is supported and observable.
        status: a :class:`~planarloc.robust.status.Status`: ``success`` or the reason it failed
            (a string of a member's value is converted to that member).
        message: a human-readable explanation.
        inliers: one (N_k,) bool array per input pair.
        num_inliers: total 2D-2D inliers.
        num_inliers_3d: inlier 2D-3D constraints (tracks / depth).
        iterations: minimal samples drawn.
        position_std_m: standard deviation of the query position along its worst axis, from
            the refinement's covariance (inf when unobservable, nan without refinement).
        unreliable_pose: for ``degenerate_scale`` the best (unobservable-position) pose, for
            diagnostics only; None otherwise.
        stats: counters per check and time per stage.
        references: names of the reference images used (filled by the Localizer).
        covariance: for a success, the (6, 6) covariance of ``world_from_camera`` in the order of
            ROS' ``PoseWithCovariance``: the camera centre (x, y, z in the map's world frame,
            metres), then the rotation (a rotation vector about the world axes, radians):
            ``world_from_camera' = (Exp(φ) R_wc, c + δc)``. Its position block's largest
            eigenvalue is ``position_std_m²``. None otherwise.
        model: motion model of the returned pose: ``"planar"`` (yaw + translation in the
            gravity-levelled plane of the references, the paper's model) or ``"6dof"`` (the
            planar model did not fit and 6DoF hypotheses won); empty on failure before a
            model was chosen.
        map_prior: the map pose prior the estimate assumed, ``(rotation std in degrees,
            position std in metres)`` per map image (filled by the Localizer: the map's own
            measurement, raised where the retrieved images disagree); None if not known.
        keypoint_budget: 0 when the estimate used every keypoint of the query and its map images;
            else it used the first (strongest) ``keypoint_budget`` of each (filled by the
            Localizer: its coarse pass,
            :attr:`~planarloc.localize.localizer_config.LocalizerConfig.coarse_keypoints`).
    """

    pose: Pose | None
    success: bool
    status: Status
    message: str
    inliers: list[np.ndarray]
    num_inliers: int = 0
    num_inliers_3d: int = 0
    iterations: int = 0
    position_std_m: float = float("nan")
    unreliable_pose: Pose | None = None
    stats: RansacStatistics = field(default_factory=RansacStatistics)
    references: list[str] = field(default_factory=list)
    model: str = ""
    covariance: np.ndarray | None = None
    map_prior: tuple[float, float] | None = None
    keypoint_budget: int = 0

    def __post_init__(self) -> None:
        status = Status.of(self.status)
        if isinstance(status, Status):  # else a status made outside the estimators, kept as given
            self.status = status

    def to_dict(self) -> dict:
        """JSON-serialisable summary (for result files)."""
        d = {
            "success": self.success,
            "status": self.status,
            "message": self.message,
            "num_inliers": int(self.num_inliers),
            "num_inliers_3d": int(self.num_inliers_3d),
            "num_matches": [int(len(m)) for m in self.inliers],
            "iterations": int(self.iterations),
            "position_std_m": None if not np.isfinite(self.position_std_m) else float(self.position_std_m),
            "stats": {k: v for k, v in vars(self.stats).items() if k != "time_s"},
            "time_s": dict(self.stats.time_s),
            "references": list(self.references),
            "model": self.model,
            "keypoint_budget": int(self.keypoint_budget),
        }
        if self.pose is not None:
            d["quat_wxyz"] = [float(v) for v in self.pose.quat_wxyz]
            d["t"] = [float(v) for v in self.pose.t]
        if self.covariance is not None:
            d["covariance_xyz_rotvec"] = [[float(v) for v in row] for row in self.covariance]
        return d
