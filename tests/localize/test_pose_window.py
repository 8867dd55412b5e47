"""The stream's sliding window: nodes and factors, solving, marginalising the oldest node into a
prior, replacing a motion, restarting at a node, and the kidnap monitor that reads it."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import Pose
from planarloc.geometry.pose_covariance import covariance_stds
from planarloc.localize.kidnap import KidnapMonitor
from planarloc.localize.motion_model import Motion
from planarloc.localize.pose_window import PoseWindow

STEP = Pose(np.eye(3), [0.0, 0.0, -1.0])  # 1 m forward (cur_from_prev)
FIX_COV = np.diag([1e-4] * 3 + [0.01] * 3)  # 0.57°, 0.1 m
MOTION_COV = np.diag([1e-4] * 3 + [0.04] * 3)  # 0.57°, 0.2 m


def _forward(n: int) -> PoseWindow:
    w = PoseWindow(8)
    w.start(Pose.identity(), FIX_COV, 0.0)
    for k in range(1, n):
        w.append(Motion(STEP, MOTION_COV, "visual"), 0.1 * k)
    return w


def test_a_chain_of_motions_predicts_and_grows_the_covariance() -> None:
    w = _forward(4)
    assert np.allclose(w.current.pose.center, [0, 0, 3])
    w.marginalize()
    pos, _ = covariance_stds(w.covariance)
    # the fix and three motions add up (plus a little from the rotations' lever arm)
    assert np.sqrt(0.01 + 3 * 0.04) <= pos < 1.01 * np.sqrt(0.01 + 3 * 0.04)
    assert w.node_at(0.2) == 2 and w.node_at(0.25) is None
    assert w.last_fixed() == 0 and w.last_absolute() == 0


def test_an_absolute_factor_pulls_the_chain_and_shrinks_the_covariance() -> None:
    w = _forward(4)
    truth = Pose(np.eye(3), [0.0, 0.0, -3.3])  # the current node is really 3.3 m ahead
    w.add_absolute(3, truth, FIX_COV)
    assert w.dirty
    w.solve()
    assert not w.dirty and w.exact
    assert 3.0 < w.current.pose.center[2] <= 3.3
    assert covariance_stds(w.covariance)[0] < 0.1 + 1e-9


def test_dropping_the_oldest_node_keeps_what_it_knew() -> None:
    w = _forward(4)
    w.marginalize()
    before = w.covariance.copy()
    w.drop_oldest()
    assert len(w) == 3 and w.nodes[0].stamp == pytest.approx(0.1)
    w.marginalize()
    assert np.allclose(w.covariance, before, atol=1e-9)


def test_a_replaced_motion_is_adopted_with_its_source() -> None:
    w = _forward(3)
    weak = Motion(Pose(np.eye(3), [0.0, 0.0, -2.0]), np.diag([1e-2] * 3 + [1.0] * 3), "constant")
    alt = w.with_motion(2, weak)
    assert np.allclose(alt.poses[2].center, [0, 0, 3])
    assert np.allclose(w.current.pose.center, [0, 0, 2])  # not adopted yet
    w.adopt(alt, "visual_rejected")
    assert w.current.source == "visual_rejected" and w.current.visual is None
    assert np.allclose(w.current.pose.center, [0, 0, 3])
    assert covariance_stds(w.covariance)[0] > 1.0


def test_a_restart_keeps_the_motions_measured_since() -> None:
    w = _forward(5)
    far = Pose(np.eye(3), [-50.0, 0.0, 0.0])
    w.restart_at(2, far, FIX_COV)
    w.rechain(0)
    assert len(w) == 3 and w.nodes[0].fixed and not w.nodes[1].fixed
    assert np.allclose(w.current.pose.center, [50.0, 0.0, 2.0])
    assert w.dirty


def test_agreeing_rejected_fixes_confirm_a_kidnap_and_disagreeing_ones_restart_the_count() -> None:
    w = _forward(4)
    monitor = KidnapMonitor(gate=22.46, confirmations=2)
    there = Pose(np.eye(3), [-40.0, 0.0, 0.0])  # centre (40, 0, 0)
    carry = lambda c, node: w.carried(
        c.pose, c.covariance, w.node_at(c.stamp), node, lambda i, dt: np.zeros((6, 6))
    )
    monitor.consider(there, FIX_COV, 0.1, lambda c: carry(c, 1))
    assert monitor.suspected and monitor.confirmed() is None
    elsewhere = Pose(np.eye(3), [40.0, 0.0, 0.0])
    monitor.consider(elsewhere, FIX_COV, 0.2, lambda c: carry(c, 2))
    assert monitor.candidate.count == 1  # disagreed: a new candidate
    moved = Pose(np.eye(3), [40.0, 0.0, -1.0])  # `elsewhere` one step later
    monitor.consider(moved, FIX_COV, 0.3, lambda c: carry(c, 3))
    assert monitor.confirmed() is not None and monitor.confirmed().count == 2
    monitor.clear()
    assert not monitor.suspected and not monitor.doubt
