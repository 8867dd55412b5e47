"""The stream's motion model: what moved the camera between two frames, and how sure that is.

Three sources, in order of preference (:class:`MotionModel`):

- **wheel odometry** (``cam_from_odom`` poses): its difference, with a std proportional to the
  distance and angle plus a floor;
- **visual odometry** (:class:`VisualStep`: the tracks' rotation and unit direction of motion):
  no scale of its own, so its length is the **speed** times the time between the stamps. The
  speed is a line fitted to the accepted fixes' speeds (:class:`SpeedFit`), so that an
  accelerating robot is not extrapolated too slow;
- **constant velocity**: the last step repeated at the measured speed, with a large std.

What visual odometry does not know is in its std along the motion (:meth:`MotionModel.visual`):
the speed's own std (from the fixes' stds, :class:`SpeedFit`), a change of speed the fixes have
not seen (``SPEED_CHANGE_STD``), and the **scale doubt** (:class:`ScaleDoubt`). The steps since the
last absolute pose share one speed, so their length errors add up, not in quadrature: after ``T``
seconds of visual odometry the along-track std is ``f(T) = σ_v·T + SPEED_CHANGE_STD·T²/2`` (``σ_v``
the speed's std, relative scale doubt included), and a step from ``T₀`` to ``T₀ + dt`` carries
``sqrt(f(T₀ + dt)² − f(T₀)²)``: chained, the steps' variances sum to ``f(T)²`` exactly.
The scale doubt: how far the lengths that speed × stamp gap predicted
were from the lengths the absolute poses then measured. A stamp gap that lies about the time
(a driver that stamps at its nominal rate while frames are lost, a recording replayed with
invented stamps) makes those lengths wrong by whole multiples; the doubt learns it from the
first contradictions and keeps the predictions honest until the lengths agree again.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import pairwise

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.geometry.pose_covariance import displacement_covariance
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.tracking import direction_basis
from planarloc.robust.pose_graph import so3_log

#: visual-odometry speed: from this many of the latest fixes (:meth:`MotionModel.update_speed`)
SPEED_FIXES = 10
#: the speed model's acceleration is at most this (m/s²), and applied at most this far from its data (s)
MAX_ACCELERATION, MAX_EXTRAPOLATION_S = 5.0, 1.0
#: an unmodelled change of speed over a visual step (m/s², as a std): the fitted line already
#: carries the measured acceleration, this is what the fixes have not seen yet
SPEED_CHANGE_STD = 1.5
#: a robot that stood still may speed up again to the largest speed of this many seconds before
#: (:meth:`MotionModel.visual`'s regain term): a stop can outlast the fixes kept for the speed
REGAIN_MEMORY_S = 10.0
#: a fix's position is never known better than this (m), for the speed's std
MIN_FIX_STD_M = 0.01
#: rotation std of the constant-velocity guess (degrees)
CONSTANT_ROTATION_STD_DEG = 20.0
#: fix-to-fix speeds whose second difference exceeds this fraction of the speed (beyond the fixes'
#: noise) say that the stamp gaps are not the times between the frames
STAMP_DOUBT_RATIO = 0.2
#: the relative std of visual odometry's length while the stamps are in doubt: a lost frame under
#: a nominal-rate stamp doubles a step's true length
DOUBTED_STAMPS_SCALE_STD = 1.0
#: the same before four fixes have shown that the stamp gaps are the times the camera moved
UNVOUCHED_STAMPS_SCALE_STD = 0.3
#: fix-to-fix speeds kept to judge the stamps
SPEEDS_KEPT = 10
#: a visual step's relative length std is at least this many times the relative jumps between
#: consecutive fix-to-fix speeds (a step is shorter than a fix-to-fix segment, and noisier)
SCATTER_SCALE = 2.0
#: stamps that lied once stay in doubt for this many accepted fixes (a driver that stamps at its
#: nominal rate over lost frames does it again)
STAMP_DOUBT_FIXES = 30
#: visual odometry farther than this (squared Mahalanobis distance of the displacement, 3σ) from
#: the constant-velocity guess is disputed (:meth:`MotionModel.disputed`)
DISPUTE_MAHALANOBIS_SQ = 9.0


def chain_std(speed_std: float, seconds: float) -> float:
    """Along-track std (m) of visual odometry chained over ``seconds`` from an absolute pose at
    one speed of std ``speed_std`` (m/s), with an unseen change of speed of std ``SPEED_CHANGE_STD``:
    ``σ_v·T + SPEED_CHANGE_STD·T²/2`` (module docstring)."""
    return speed_std * seconds + SPEED_CHANGE_STD * seconds**2 / 2


@dataclass(frozen=True)
class VisualStep:
    """Visual odometry between two frames before it is given a length.

    Attributes:
        R: (3, 3) rotation ``cur_from_prev``.
        direction: (3,) unit direction of the current centre in the previous camera's frame.
        stamp: the current frame's stamp (s).
        dt: the time since the previous frame (s).
        covariance: (5, 5) covariance of (rotation, direction) from the tracks, or None.
        disputed_m: the constant-velocity model's disagreement with it (:meth:`MotionModel.disputed`),
            a std added on every position axis.
        since_anchor_s: time from the last absolute pose (a fix, tracked map points) before the
            step to the step's start: the steps in between share its speed error.
    """

    R: np.ndarray
    direction: np.ndarray
    stamp: float
    dt: float
    covariance: np.ndarray | None = None
    disputed_m: float = 0.0
    since_anchor_s: float = 0.0


@dataclass(frozen=True)
class Motion:
    """The motion since the previous frame, ``cur_from_prev``, with its (6, 6) pose-graph covariance.

    ``source``: ``"odometry"``, ``"visual"``, ``"constant"``, ``"none"`` (first frame) or
    ``"visual_rejected"``; ``model``: ``"planar"`` / ``"6dof"`` for visual odometry, else empty;
    ``visual``: the visual step it was scaled from (to scale it again when the speed changes).
    """

    cur_from_prev: Pose
    covariance: np.ndarray
    source: str
    model: str = ""
    visual: VisualStep | None = None

    @staticmethod
    def none() -> Motion:
        return Motion(Pose.identity(), np.zeros((6, 6)), "none")


@dataclass(frozen=True)
class SpeedFit:
    """A line through the fixes' speeds: ``speed`` (m/s) at ``t_ref`` and its ``acceleration``;
    ``covariance``: (2, 2) of (speed, acceleration) from the fixes' position stds."""

    t_ref: float
    speed: float
    acceleration: float
    covariance: np.ndarray | None = field(default=None, compare=False)

    def at(self, stamp: float) -> float:
        """The speed at ``stamp``, extrapolated at most ``MAX_EXTRAPOLATION_S``, never negative."""
        dt = float(np.clip(stamp - self.t_ref, -MAX_EXTRAPOLATION_S, MAX_EXTRAPOLATION_S))
        return max(self.speed + self.acceleration * dt, 0.0)

    def std_at(self, stamp: float) -> float:
        """The std of :meth:`at` (m/s): the line's uncertainty at ``stamp`` (0 without a covariance)."""
        if self.covariance is None:
            return 0.0
        dt = float(np.clip(stamp - self.t_ref, -MAX_EXTRAPOLATION_S, MAX_EXTRAPOLATION_S))
        J = np.array([1.0, dt])
        return float(np.sqrt(max(J @ self.covariance @ J, 0.0)))


class ScaleDoubt:
    """The relative std of visual odometry's length, learned from how wrong it was.

    Each time an absolute pose (a fix, or the tracked map points) measures the distance moved
    since the previous absolute pose over steps scaled by speed × stamp gap, the ratio of the
    measured to the predicted length is an observation of the scale error. The doubt is the
    root mean square of the latest ``window`` observations of ``|ratio − 1|`` (so one large
    error is remembered for ``window`` measurements), floored by the configured
    ``vo_scale_std`` and capped at ``max_std``.
    """

    def __init__(self, floor: float, max_std: float = 2.0, window: int = 8) -> None:
        self.floor, self.max_std, self.window = float(floor), float(max_std), int(window)
        self.errors: list[float] = []

    def reset(self) -> None:
        self.errors = []

    def observe(self, measured_m: float, predicted_m: float, std_m: float) -> None:
        """One measured length against the predicted one; lengths within the measurement's own
        std (``std_m``) of each other say nothing about the scale and count as agreement."""
        if predicted_m < 0.2 or not np.isfinite(measured_m):
            return
        excess = max(abs(measured_m - predicted_m) - std_m, 0.0)
        self.errors.append(min(excess / predicted_m, self.max_std))
        del self.errors[: -self.window]

    @property
    def std(self) -> float:
        if not self.errors:
            return self.floor
        rms = float(np.sqrt(np.mean(np.square(self.errors))))
        return float(np.clip(max(rms, max(self.errors[-2:])), self.floor, self.max_std))


def fit_speed(stamps: np.ndarray, centers: np.ndarray, stds: np.ndarray) -> SpeedFit:
    """The speed along a path through fixes, with its covariance.

    The distance travelled along the path (the fixes' centres joined in order) is fitted by
    weighted least squares as a function of time, ``s(τ) = s₀ + v·τ + a·τ²/2`` with ``τ`` from the
    last fix (a line, ``a = 0``, with fewer than four fixes; ``|a|`` at most
    ``MAX_ACCELERATION``), each fix weighted by its position std. Fitting the positions rather
    than differencing consecutive fixes uses every fix once: the speed's std is that of the fit.

    Args:
        stamps: (N,) increasing times (s), N ≥ 2.
        centers: (N, 3) the fixes' camera centres.
        stds: (N,) their position stds (m), > 0.
    Returns:
        :class:`SpeedFit` at the last fix, with the (2, 2) covariance of (speed, acceleration).
    """
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centers, axis=0), axis=1))])
    tau = stamps - stamps[-1]
    w = 1.0 / np.square(stds)
    quadratic = len(stamps) >= 4
    A = np.stack([np.ones_like(tau), tau, tau**2 / 2] if quadratic else [np.ones_like(tau), tau], axis=1)
    info = A.T @ (A * w[:, None])
    params = np.linalg.solve(info, A.T @ (s * w))
    cov = np.linalg.inv(info)
    accel = float(params[2]) if quadratic else 0.0
    if abs(accel) > MAX_ACCELERATION:  # clipped: the line through what the parabola leaves
        accel = float(np.clip(accel, -MAX_ACCELERATION, MAX_ACCELERATION))
        A2 = A[:, :2]
        info = A2.T @ (A2 * w[:, None])
        params = np.linalg.solve(info, A2.T @ ((s - accel * tau**2 / 2) * w))
        cov = np.linalg.inv(info)
    speed_cov = cov[1:3, 1:3] if cov.shape[0] == 3 else np.diag([cov[1, 1], 0.0])
    return SpeedFit(float(stamps[-1]), max(float(params[1]), 0.0), accel, speed_cov)


class MotionModel:
    """Odometry, visual odometry and constant-velocity motions with honest covariances, and the
    speed that gives visual odometry its length (module docstring).

    Args:
        config: the stream's :class:`SequenceConfig` (``odometry_*``, ``vo_*``, ``max_speed_mps``).
    """

    def __init__(self, config: SequenceConfig) -> None:
        self.config = config
        self.doubt = ScaleDoubt(config.vo_scale_std)
        self.reset()

    def reset(self) -> None:
        self.speed: float | None = None
        self.fit: SpeedFit | None = None
        self.fixes: list[tuple[float, np.ndarray, float]] = []  # stamp, centre, position std
        self.doubt.reset()
        self.stamps_doubted = True  # until four fixes have shown that stamp gaps are times
        self.speed_scatter = 0.0  # relative jumps between consecutive fix-to-fix speeds
        self.recent_speed: float | None = None  # the largest fix-to-fix speed of the last REGAIN_MEMORY_S
        self._speeds_seen: list[tuple[float, float]] = []  # (stamp, fix-to-fix speed ending there)
        self._doubted_fixes = 0
        self._vouched = False

    @property
    def scale_std(self) -> float:
        """The relative std of a visual step's length now (module docstring)."""
        std = self.doubt.std if self.fit is not None else max(self.config.vo_first_scale_std, self.doubt.std)
        std = max(std, SCATTER_SCALE * self.speed_scatter)
        if self._doubted_fixes > 0:
            return max(std, DOUBTED_STAMPS_SCALE_STD)
        return std if self._vouched else max(std, UNVOUCHED_STAMPS_SCALE_STD)

    def restart(self, stamp: float, center: np.ndarray, keep_speed: bool = False) -> None:
        """A new start at a fix (the stream's first, or a confirmed kidnap's): its centre is the
        only one the speed is measured from; the last speed stays as a guess when ``keep_speed``."""
        self.fixes = [(stamp, np.asarray(center, dtype=float), 0.0)]
        self.stamps_doubted = self._doubted_fixes > 0 or not self._vouched
        self.fit = None
        if not keep_speed:
            self.speed = None

    def add_fix(self, stamp: float, center: np.ndarray, std_m: float = 0.0) -> None:
        """An accepted fix's centre at ``stamp`` with its position std ``std_m``."""
        self.fixes.append((stamp, np.asarray(center, dtype=float), float(std_m)))
        del self.fixes[: -SPEEDS_KEPT - 1]
        if self._stamps_contradicted():
            self._doubted_fixes = STAMP_DOUBT_FIXES
        else:
            self._doubted_fixes = max(self._doubted_fixes - 1, 0)
        self._vouched = self._vouched or len(self.fixes) >= 4  # a restart does not change the camera
        self.stamps_doubted = self._doubted_fixes > 0 or not self._vouched

    def _stamps_contradicted(self) -> bool:
        """Whether the fix-to-fix speeds zigzag: a speed that changes smoothly (accelerating,
        braking) has second differences ``v₋ − 2v + v₊`` near zero, a stamp gap that is not the
        time the camera moved (lost frames under nominal-rate stamps, invented stamps) makes one
        segment fast and its neighbours slow. Contradicted when a second difference exceeds
        ``STAMP_DOUBT_RATIO`` of the speed beyond the fixes' noise (a quarter of their reported
        stds, which are several times their errors)."""
        fixes = sorted(self.fixes, key=lambda f: f[0])
        seg = [
            (float(np.linalg.norm(b[1] - a[1])) / (b[0] - a[0]), (a[2] + b[2]) / (b[0] - a[0]))
            for a, b in pairwise(fixes)
            if b[0] > a[0]
        ]
        for (v0, n0), (v1, n1), (v2, n2) in zip(seg, seg[1:], seg[2:]):
            noise = (n0 + 2 * n1 + n2) / 4
            if abs(v0 - 2 * v1 + v2) - noise > STAMP_DOUBT_RATIO * max(v0, v1, v2):
                return True
        return False

    # ---- the speed ------------------------------------------------------------------------
    def speed_at(self, stamp: float) -> float | None:
        """The speed at ``stamp`` (:meth:`update_speed`), else the last one measured."""
        return self.speed if self.fit is None else self.fit.at(stamp)

    def update_speed(self, now: float) -> bool:
        """Speed from the raw fixes, not the fused poses (fused poses follow visual odometry,
        whose length comes from this speed: a feedback loop that would keep any initial error):
        :func:`fit_speed` over the last ``SPEED_FIXES``. Returns whether it changed."""
        fixes = sorted(self.fixes, key=lambda f: f[0])[-SPEED_FIXES:]
        fixes = [f for k, f in enumerate(fixes) if k == 0 or f[0] > fixes[k - 1][0]]
        if len(fixes) < 2:
            return False
        fit = fit_speed(
            np.array([f[0] for f in fixes]),
            np.stack([f[1] for f in fixes]),
            np.maximum([f[2] for f in fixes], MIN_FIX_STD_M),
        )
        old, self.fit = self.fit, fit
        self.speed = self.fit.at(now)
        # consecutive fix-to-fix speeds that differ beyond the fixes' noise: a step's length is at
        # least this unsure (a smooth speed change hardly shows between two segments)
        speeds = sorted(self.fixes, key=lambda f: f[0])
        segs = [
            (float(np.linalg.norm(b[1] - a[1])) / (b[0] - a[0]), (a[2] + b[2]) / (b[0] - a[0]))
            for a, b in pairwise(speeds)
            if b[0] > a[0]
        ]
        latest = speeds[-1][0]
        self._speeds_seen = [(t, v) for t, v in self._speeds_seen if t >= latest - REGAIN_MEMORY_S]
        ends = [
            (b[0], float(np.linalg.norm(b[1] - a[1])) / (b[0] - a[0]))
            for a, b in pairwise(speeds)
            if b[0] > a[0]
        ]
        self._speeds_seen += [
            (t, v) for t, v in ends if not self._speeds_seen or t > self._speeds_seen[-1][0]
        ]
        self.recent_speed = max((v for _, v in self._speeds_seen), default=self.speed)
        if len(segs) >= 2:
            jumps = [max(abs(v1 - v0) - n0 - n1, 0.0) for (v0, n0), (v1, n1) in pairwise(segs)]
            mean_v = max(float(np.mean([v for v, _ in segs])), 1e-3)
            self.speed_scatter = float(np.sqrt(np.mean(np.square(jumps)))) / mean_v
        return old != self.fit

    def first_speed(self, distance_m: float, dt: float) -> bool:
        """Before a second fix: a first speed from two absolute poses (the first fix and the
        poses of its tracked map points) ``distance_m`` apart over ``dt`` seconds. Returns
        whether it is the first speed."""
        if self.fit is not None or dt <= 0:
            return False
        old, self.speed = self.speed, distance_m / dt
        return old is None

    # ---- the motions ----------------------------------------------------------------------
    def odometry(self, cur_from_odom: Pose, prev_from_odom: Pose) -> Motion:
        """The motion between two wheel-odometry poses, std ∝ distance and angle plus a floor."""
        cfg = self.config
        motion = cur_from_odom @ prev_from_odom.inverse()
        d = motion.inverse().t
        dist = float(np.linalg.norm(d))
        angle = float(np.linalg.norm(so3_log(motion.R[None])[0]))
        along = cfg.odometry_translation_std * dist + cfg.odometry_min_std_m
        rot = cfg.odometry_rotation_std * angle + np.radians(cfg.odometry_min_rotation_std_deg)
        return Motion(motion, displacement_covariance(d, along, along, rot), "odometry")

    def visual(self, step: VisualStep, model: str = "") -> Motion:
        """Visual odometry given the length speed × ``step.dt`` (without a speed: none, with the
        std ``max_speed_mps · dt``).

        Covariance over (rotation, centre displacement ``d = dist · u``): the tracks' own (5, 5)
        covariance of rotation and direction (with their correlation), plus
        ``vo_rotation_std_deg`` and ``vo_direction_std_deg`` per axis and 2 cm across; along the
        motion the step's share of :func:`chain_std` since ``step.since_anchor_s`` (the speed's
        std: its fit's, and its relative std ``vo_first_scale_std`` before two fixes measured it,
        else the :class:`ScaleDoubt`'s), a robot speeding up again after a stop, and 5 cm."""
        cfg = self.config
        mid = step.stamp - step.dt / 2
        speed = self.speed_at(mid)
        if speed is None:
            dist, along = 0.0, cfg.max_speed_mps * step.dt
        else:
            dist = speed * step.dt
            # a robot at less than half its recent speed may be speeding up again (stop-and-go)
            regain = max(0.5 * (self.recent_speed or 0.0) - speed, 0.0) * 2.0 * step.dt
            speed_std = float(
                np.hypot(self.scale_std * speed, 0.0 if self.fit is None else self.fit.std_at(mid))
            )
            t0 = max(step.since_anchor_s, 0.0)
            chained = np.sqrt(
                max(chain_std(speed_std, t0 + step.dt) ** 2 - chain_std(speed_std, t0) ** 2, 0.0)
            )
            along = float(chained) + regain + 0.05
        across = dist * np.radians(cfg.vo_direction_std_deg) + 0.02
        u = step.direction
        cov = displacement_covariance(u, along, across, np.radians(cfg.vo_rotation_std_deg))
        if step.covariance is not None:
            B = direction_basis(u) * dist
            c5 = step.covariance
            cov[:3, :3] += c5[:3, :3]
            cov[:3, 3:] += c5[:3, 3:] @ B.T
            cov[3:, :3] += B @ c5[3:, :3]
            cov[3:, 3:] += B @ c5[3:, 3:] @ B.T
        cov[3:, 3:] += np.eye(3) * step.disputed_m**2
        return Motion(Pose(step.R, -step.R @ (u * dist)), cov, "visual", model, step)

    def disputed(self, visual: Motion, weak: Motion) -> Motion:
        """Visual odometry whose displacement the constant-velocity model disputes: a wrong
        basin of 2D-2D motion (a small step next to a turn, bas-relief) explains the tracks as
        well as the truth, and the tracks' covariance cannot say so. When the two displacements
        differ by more than ``DISPUTE_MAHALANOBIS_SQ`` under the visual one's covariance (and a
        speed is known), that difference is added to the visual motion's position std on every
        axis: two models that disagree are not surer than their disagreement."""
        if self.speed is None or visual.source != "visual":
            return visual
        g = visual.cur_from_prev.inverse().t - weak.cur_from_prev.inverse().t
        try:
            m2 = float(g @ np.linalg.solve(visual.covariance[3:, 3:], g))
        except np.linalg.LinAlgError:
            m2 = float("inf")
        if m2 <= DISPUTE_MAHALANOBIS_SQ or visual.visual is None:
            return visual
        gap = float(np.linalg.norm(g))
        return self.visual(replace(visual.visual, disputed_m=gap), visual.model)

    def constant(self, last_step: Pose | None, dt: float) -> Motion:
        """Constant velocity: ``last_step`` (the previous ``cur_from_prev``) repeated at the
        measured speed, with a large covariance (position std ``max_speed_mps · dt / 5`` plus half
        the step, rotation 20°); before a speed is measured, no motion with std
        ``max_speed_mps · dt`` (as :meth:`visual`)."""
        motion, d, known = Pose.identity(), np.zeros(3), False
        if last_step is not None and self.speed is not None:
            known = True
            d = last_step.inverse().t
            n = np.linalg.norm(d)
            if n > 1e-9:
                d = d / n * self.speed * dt
            motion = Pose(last_step.R, -last_step.R @ d)
        along = 0.5 * float(np.linalg.norm(d)) + (0.2 if known else 1.0) * self.config.max_speed_mps * dt
        cov = displacement_covariance(d, along, along, np.radians(CONSTANT_ROTATION_STD_DEG))
        return Motion(motion, cov, "constant")
