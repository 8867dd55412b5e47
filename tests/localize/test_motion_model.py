"""The stream's motion model: visual odometry's length and how sure it is, stamps that lie,
disputed visual steps, the scale doubt, constant velocity and odometry covariances."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.localize.motion_model import (
    DOUBTED_STAMPS_SCALE_STD,
    MotionModel,
    ScaleDoubt,
    SpeedFit,
    VisualStep,
    chain_std,
    fit_speed,
)
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.tracking import TrackerOptions
from planarloc.robust.pose_graph import so3_exp

FORWARD = np.array([0.0, 0.0, 1.0])


def _along_std(motion) -> float:
    u = motion.cur_from_prev.inverse().t
    u = u / np.linalg.norm(u)
    return float(np.sqrt(u @ motion.covariance[3:, 3:] @ u))


def _model_with_fixes(stamps: list[float], positions: list[float], std: float = 0.02) -> MotionModel:
    m = MotionModel(SequenceConfig())
    m.restart(stamps[0], np.array([0.0, 0.0, positions[0]]))
    for t, z in zip(stamps[1:], positions[1:]):
        m.add_fix(t, np.array([0.0, 0.0, z]), std)
    m.update_speed(stamps[-1])
    return m


def test_speed_fit_extrapolates_at_most_a_second_and_never_backwards() -> None:
    fit = SpeedFit(t_ref=10.0, speed=2.0, acceleration=-1.0)
    assert fit.at(10.5) == pytest.approx(1.5)
    assert fit.at(30.0) == pytest.approx(1.0)  # clipped to 1 s of extrapolation
    assert SpeedFit(0.0, 0.5, -5.0).at(1.0) == 0.0


def test_the_speed_fit_recovers_a_constant_acceleration_exactly() -> None:
    # s(t) = 2 t + 0.75 t² along a straight line: speed 2 + 1.5 t, acceleration 1.5
    t = np.array([0.0, 0.15, 0.3, 0.5, 0.6, 0.8])
    centers = np.stack([np.zeros_like(t), np.zeros_like(t), 2 * t + 0.75 * t**2], axis=1)
    fit = fit_speed(t, centers, np.full(len(t), 0.05))
    assert fit.t_ref == 0.8 and fit.speed == pytest.approx(2 + 1.5 * 0.8, abs=1e-9)
    assert fit.acceleration == pytest.approx(1.5, abs=1e-9)
    # with fewer than four fixes: a line, the mean speed
    line = fit_speed(t[:3], centers[:3], np.full(3, 0.05))
    assert line.acceleration == 0.0 and 2.0 < line.speed < 2 + 1.5 * 0.3


def test_the_speed_std_is_that_of_the_fit_and_covers_noisy_fixes() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(6) * 0.1
    truth = 8.0 * t
    speeds, std = [], None
    for _ in range(400):
        z = truth + rng.normal(0.0, 0.05, len(t))
        fit = fit_speed(t, np.stack([np.zeros_like(t), np.zeros_like(t), z], axis=1), np.full(len(t), 0.05))
        std = fit.std_at(t[-1])
        speeds.append(fit.speed)
    errors = np.array(speeds) - 8.0
    # calibrated both ways: the spread of the fitted speeds is the reported std
    assert np.std(errors) == pytest.approx(std, rel=0.15)
    assert np.mean(np.abs(errors) > 3 * std) < 0.01
    # quadrupling the fixes' std quadruples the speed's
    again = fit_speed(t, np.stack([np.zeros_like(t), np.zeros_like(t), truth], axis=1), np.full(len(t), 0.2))
    base = fit_speed(t, np.stack([np.zeros_like(t), np.zeros_like(t), truth], axis=1), np.full(len(t), 0.05))
    assert again.std_at(0.5) == pytest.approx(4 * base.std_at(0.5))


def test_chained_visual_steps_add_their_length_errors_linearly() -> None:
    # the steps since the last absolute pose share the speed's error: their variances sum to chain_std²
    m = _model_with_fixes([0.0, 0.1, 0.2, 0.3, 0.4], [0.0, 1.0, 2.0, 3.0, 4.0])
    var, dt = 0.0, 0.1
    for k in range(6):
        step = VisualStep(np.eye(3), FORWARD, 0.5 + k * dt, dt, since_anchor_s=k * dt)
        var += (_along_std(m.visual(step)) - 0.05) ** 2  # without the per-step 5 cm
    speed_std = float(np.hypot(m.scale_std * m.speed_at(0.75), m.fit.std_at(0.75)))
    assert np.sqrt(var) == pytest.approx(chain_std(speed_std, 0.6), rel=0.05)
    # a step far from its anchor is less sure than the same step just after a fix
    near = m.visual(VisualStep(np.eye(3), FORWARD, 0.5, dt, since_anchor_s=0.0))
    far = m.visual(VisualStep(np.eye(3), FORWARD, 0.5, dt, since_anchor_s=0.5))
    assert _along_std(far) > 2 * _along_std(near) - 0.05


def test_honest_stamps_give_the_speed_and_a_small_length_std() -> None:
    # 10 m/s, a fix every 0.1 s with consistent stamps
    m = _model_with_fixes([0.0, 0.1, 0.2, 0.3, 0.4], [0.0, 1.0, 2.0, 3.0, 4.0])
    assert m.speed == pytest.approx(10.0, rel=1e-6)
    assert not m.stamps_doubted
    motion = m.visual(VisualStep(np.eye(3), FORWARD, 0.5, 0.1))
    assert np.allclose(motion.cur_from_prev.inverse().t, [0, 0, 1.0])
    assert _along_std(motion) < 0.25


def test_stamps_that_lie_about_lost_frames_make_the_length_unsure() -> None:
    # nominal 0.1 s stamps, but a frame was lost between the 2nd and 3rd fix (2 m in "0.1 s")
    m = _model_with_fixes([0.0, 0.1, 0.2, 0.3, 0.4], [0.0, 1.0, 3.0, 4.0, 5.0])
    assert m.stamps_doubted
    assert m.scale_std >= DOUBTED_STAMPS_SCALE_STD
    motion = m.visual(VisualStep(np.eye(3), FORWARD, 0.5, 0.1))
    length = float(np.linalg.norm(motion.cur_from_prev.t))
    # a step twice the predicted length is within 3 std
    assert 2 * length - length <= 3 * _along_std(motion)


def test_the_first_fixes_cannot_vouch_for_the_stamps() -> None:
    m = _model_with_fixes([0.0, 0.1], [0.0, 1.0])
    assert m.stamps_doubted
    assert not _model_with_fixes([0.0, 0.1, 0.2, 0.3], [0.0, 1.0, 2.0, 3.0]).stamps_doubted


def test_a_visual_step_the_constant_velocity_model_disputes_is_not_surer_than_the_dispute() -> None:
    m = _model_with_fixes([0.0, 0.1, 0.2, 0.3, 0.4], [0.0, 1.0, 2.0, 3.0, 4.0])
    weak = m.constant(Pose(np.eye(3), [0.0, 0.0, -1.0]), 0.1)  # 1 m forward again
    sideways = np.array([np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))])
    visual = m.visual(VisualStep(np.eye(3), sideways, 0.5, 0.1))
    disputed = m.disputed(visual, weak)
    gap = np.linalg.norm(visual.cur_from_prev.inverse().t - weak.cur_from_prev.inverse().t)
    assert np.linalg.eigvalsh(disputed.covariance[3:, 3:])[0] >= gap**2
    # the dispute survives a new speed (visual steps are scaled again from their record)
    assert disputed.visual is not None and disputed.visual.disputed_m == pytest.approx(gap)
    again = m.visual(disputed.visual)
    assert np.allclose(again.covariance, disputed.covariance)
    # an agreeing step is left alone
    ahead = m.visual(VisualStep(np.eye(3), FORWARD, 0.5, 0.1))
    assert m.disputed(ahead, weak) is ahead


def test_the_scale_doubt_grows_with_contradictions_and_forgets_them() -> None:
    d = ScaleDoubt(0.1, window=4)
    assert d.std == 0.1
    d.observe(measured_m=2.0, predicted_m=1.0, std_m=0.05)
    assert d.std == pytest.approx(0.95)
    for _ in range(4):
        d.observe(1.0, 1.0, 0.05)
    assert d.std == 0.1
    d.observe(1.04, 1.0, 0.05)  # within the measurement's own std: agreement
    assert d.std == 0.1


def test_without_a_speed_visual_odometry_has_no_length_and_a_wide_std() -> None:
    m = MotionModel(SequenceConfig(max_speed_mps=10.0))
    motion = m.visual(VisualStep(so3_exp(np.array([[0.0, 0.1, 0.0]]))[0], FORWARD, 0.1, 0.1))
    assert np.allclose(motion.cur_from_prev.t, 0)
    assert motion.covariance[5, 5] == pytest.approx(1.0)  # max_speed_mps · dt along the direction


def test_odometry_motion_and_its_std_grow_with_distance_and_angle() -> None:
    cfg = SequenceConfig()
    m = MotionModel(cfg)
    prev = Pose.identity()
    cur = Pose(so3_exp(np.array([[0.0, 0.2, 0.0]]))[0], [0.0, 0.0, -2.0])
    motion = m.odometry(cur, prev)
    assert np.allclose((motion.cur_from_prev @ prev).matrix, cur.matrix)
    along = cfg.odometry_translation_std * np.linalg.norm(cur.inverse().t) + cfg.odometry_min_std_m
    assert np.sqrt(motion.covariance[5, 5]) == pytest.approx(along, rel=1e-6)
    rot = cfg.odometry_rotation_std * 0.2 + np.radians(cfg.odometry_min_rotation_std_deg)
    assert np.sqrt(motion.covariance[0, 0]) == pytest.approx(rot, rel=1e-6)


def test_the_visual_odometry_model_is_set_in_one_place() -> None:
    assert SequenceConfig(vo_model="planar").tracker.model == "planar"
    with pytest.raises(InputError, match="vo_model"):
        SequenceConfig(tracking=TrackerOptions(model="planar"))
