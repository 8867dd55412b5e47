"""Pose graph: Jacobians, recovery of a noisy chain, covariances, marginalisation."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.robust.pose_graph import (
    AbsoluteFactor,
    RelativeFactor,
    _Packed,
    _retract,
    _unpack,
    marginal_covariances,
    marginalize_first,
    so3_exp,
    solve_pose_graph,
)


def _random_pose(rng: np.random.Generator) -> Pose:
    return Pose(so3_exp(rng.normal(size=3))[0], rng.normal(size=3))


def _cov(rot_std: float, pos_std: float) -> np.ndarray:
    return np.diag([rot_std**2] * 3 + [pos_std**2] * 3)


def test_analytic_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    poses = [_random_pose(rng) for _ in range(3)]
    absolute = [
        AbsoluteFactor(0, _random_pose(rng), _cov(0.1, 0.3)),
        AbsoluteFactor(2, _random_pose(rng), _cov(0.05, 1)),
    ]
    relative = [
        RelativeFactor(0, 1, _random_pose(rng), _cov(0.02, 0.1) + 0.001),
        RelativeFactor(1, 2, _random_pose(rng), _cov(0.2, 0.5)),
    ]
    packed = _Packed(3, absolute, relative)
    R0, c0 = _unpack(poses)
    J = packed.jacobian(R0, c0)
    eps = 1e-6
    Jn = np.zeros_like(J)
    for k in range(18):
        dx = np.zeros(18)
        dx[k] = eps
        rp = packed.residuals(*_retract(R0, c0, dx))[0]
        rm = packed.residuals(*_retract(R0, c0, -dx))[0]
        Jn[:, k] = (rp - rm) / (2 * eps)
    np.testing.assert_allclose(J, Jn, rtol=1e-4, atol=1e-5)


def _chain(rng: np.random.Generator, n: int) -> list[Pose]:
    poses, yaw, c = [], 0.0, np.zeros(3)
    for _ in range(n):
        R = so3_exp([[0, yaw, 0]])[0]
        poses.append(Pose.from_center(R, c))
        yaw += rng.uniform(-0.3, 0.3)
        c = c + np.array([np.sin(yaw), 0, np.cos(yaw)]) * rng.uniform(0.5, 1.5)
    return poses


def test_fixes_and_odometry_fuse_better_than_either() -> None:
    rng = np.random.default_rng(1)
    truth = _chain(rng, 8)
    rel_cov, abs_cov = _cov(np.radians(0.2), 0.02), _cov(np.radians(1.0), 0.3)
    relative = []
    for i in range(7):
        m = truth[i + 1] @ truth[i].inverse()
        noisy = Pose(so3_exp(rng.normal(0, np.radians(0.2), (1, 3)))[0] @ m.R, m.t + rng.normal(0, 0.02, 3))
        relative.append(RelativeFactor(i, i + 1, noisy, rel_cov))
    fixes = []
    for k, p in enumerate(truth):
        noisy = Pose.from_center(
            so3_exp(rng.normal(0, np.radians(1), (1, 3)))[0] @ p.R, p.center + rng.normal(0, 0.3, 3)
        )
        fixes.append(AbsoluteFactor(k, noisy, abs_cov))
    sol = solve_pose_graph([Pose.identity()] * 8, fixes, relative)
    fused = np.mean([pose_errors(a, b)[0] for a, b in zip(sol.poses, truth)])
    raw = np.mean([np.linalg.norm(f.pose.center - p.center) for f, p in zip(fixes, truth)])
    assert fused < 0.6 * raw
    std = np.sqrt(np.diagonal(sol.covariances[:, 3:, 3:], axis1=1, axis2=2))
    assert np.all(std < 0.3) and np.all(std > 0.02)  # fused: better than one fix, worse than odometry alone
    # exact data: the solution is exact
    exact_rel = [RelativeFactor(i, i + 1, truth[i + 1] @ truth[i].inverse(), rel_cov) for i in range(7)]
    sol = solve_pose_graph([Pose.identity()] * 8, [AbsoluteFactor(0, truth[0], abs_cov)], exact_rel)
    assert max(pose_errors(a, b)[0] for a, b in zip(sol.poses, truth)) < 1e-8


def test_prediction_covariance_grows_with_each_motion() -> None:
    rng = np.random.default_rng(2)
    truth = _chain(rng, 5)
    rel = [RelativeFactor(i, i + 1, truth[i + 1] @ truth[i].inverse(), _cov(0.01, 0.1)) for i in range(4)]
    cov = marginal_covariances(truth, [AbsoluteFactor(0, truth[0], _cov(0.01, 0.1))], rel)
    pos_var = np.trace(cov[:, 3:, 3:], axis1=1, axis2=2)
    assert np.all(np.diff(pos_var) > 0)
    assert np.isinf(marginal_covariances(truth, [], rel)).all()  # not anchored


def test_marginalising_the_first_node_keeps_the_solution_of_the_chain() -> None:
    rng = np.random.default_rng(3)
    truth = _chain(rng, 5)
    rel = [RelativeFactor(i, i + 1, truth[i + 1] @ truth[i].inverse(), _cov(0.01, 0.05)) for i in range(4)]
    fixes = [
        AbsoluteFactor(k, Pose.from_center(p.R, p.center + rng.normal(0, 0.2, 3)), _cov(0.02, 0.2))
        for k, p in enumerate(truth)
    ]
    full = solve_pose_graph(truth, fixes, rel)
    a, r = marginalize_first(full.poses, fixes, rel)
    reduced = solve_pose_graph(full.poses[1:], a, r)
    for p, q in zip(full.poses[1:], reduced.poses):
        assert pose_errors(p, q)[0] < 1e-6
    np.testing.assert_allclose(reduced.covariances, full.covariances[1:], rtol=2e-2, atol=1e-7)


def test_bad_graphs_are_input_errors() -> None:
    with pytest.raises(InputError, match="anchor"):
        solve_pose_graph([Pose.identity()], [], [])
    with pytest.raises(InputError, match="node"):
        solve_pose_graph([Pose.identity()], [AbsoluteFactor(3, Pose.identity(), np.eye(6))], [])
    with pytest.raises(InputError, match="positive definite"):
        solve_pose_graph([Pose.identity()], [AbsoluteFactor(0, Pose.identity(), -np.eye(6))], [])


def test_a_factor_stores_its_covariance_as_an_array_and_names_it_when_it_is_wrong() -> None:
    f = AbsoluteFactor(0, Pose.identity(), [[float(i == j) for j in range(6)] for i in range(6)])
    assert isinstance(f.covariance, np.ndarray) and f.covariance.shape == (6, 6)
    with pytest.raises(InputError, match=r"AbsoluteFactor\.covariance"):
        AbsoluteFactor(0, Pose.identity(), np.eye(3))
    with pytest.raises(InputError, match=r"RelativeFactor\.covariance"):
        RelativeFactor(0, 1, Pose.identity(), np.full((6, 6), np.nan))
