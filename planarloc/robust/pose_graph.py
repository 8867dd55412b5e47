"""A small pose graph over camera poses: relative-motion factors and absolute fixes.

Nodes are ``cam_from_world`` poses. Every factor compares a measured quantity with the one
implied by the nodes in a 6-vector ``(rotation, position)`` and is weighted by the inverse of
its (6, 6) covariance in that order (radians, metres):

* :class:`AbsoluteFactor` on node ``k`` (a localization fix or a prior):
  ``r = (log(R_k R_zᵀ), c_k − c_z)`` with ``R``, ``c`` rotation and camera centre (world frame).
* :class:`RelativeFactor` from node ``i`` to node ``j`` (odometry, visual odometry):
  ``r = (log(R_j R_iᵀ R_mᵀ), R_i (c_j − c_i) − d_m)`` where ``j_from_i = (R_m, t_m)`` is the
  measured motion and ``d_m = −R_mᵀ t_m`` the centre of camera ``j`` in camera ``i``'s frame.

The tangent space of a node is ``(ω, δc)`` with ``R = exp([ω]×) R₀``, ``c = c₀ + δc``; the
covariances returned by :func:`solve_pose_graph` are in this space (world frame), so a
position block is directly the covariance of the camera centre in metres².

The graph is solved by Levenberg-Marquardt on the normal equations (analytic Jacobians,
re-linearised at every accepted step, dense: a window has at most a few dozen nodes);
marginal covariances are the blocks of ``(JᵀJ)⁻¹`` at the solution (Gauss-Newton
approximation).

References:
    Grisetti et al., "A Tutorial on Graph-Based SLAM", IEEE ITS Magazine 2010 (factor form);
    Barfoot, "State Estimation for Robotics", 2017, eq. (7.77) (left Jacobian of SO(3)).
    Deviation: window marginalisation (:func:`marginalize_first`) keeps a Gaussian prior on
    the next node only, which is exact for a chain (relative factors between consecutive
    nodes) linearised at the current estimate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planarloc.geometry.epipolar import skew
from planarloc.geometry.pose import Pose

# SO(3) maps live in geometry.so3; imported here for the graph (and still importable from here)
from planarloc.geometry.so3 import so3_exp, so3_left_jacobian_inverse, so3_log
from planarloc.geometry.validation import InputError, check_array


def _whitener(name: str, cov: object) -> np.ndarray:
    """(6, 6) upper factor ``U`` with ``UᵀU = cov⁻¹`` (whitened residual = ``U r``)."""
    C = check_array(name, cov, (6, 6))
    C = 0.5 * (C + C.T)
    try:
        L = np.linalg.cholesky(np.linalg.inv(C))
    except np.linalg.LinAlgError:
        raise InputError(f"{name}: covariance must be symmetric positive definite") from None
    return L.T


class _Factor:
    """What the factors share: a (6, 6) ``covariance``, checked and stored as a float64 array."""

    covariance: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "covariance", check_array(f"{type(self).__name__}.covariance", self.covariance, (6, 6))
        )


@dataclass(frozen=True, eq=False)
class AbsoluteFactor(_Factor):
    """A measured pose of node ``node``.

    Attributes:
        node: index of the node.
        pose: measured ``cam_from_world``.
        covariance: (6, 6) of ``(rotation [rad], camera centre [m])``, world frame.
    """

    node: int
    pose: Pose
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class RelativeFactor(_Factor):
    """A measured motion ``j_from_i`` (camera ``i`` to camera ``j``).

    Attributes:
        i, j: node indices.
        j_from_i: the motion; its translation is metric.
        covariance: (6, 6) of ``(rotation [rad], centre of j in camera i's frame [m])``.
    """

    i: int
    j: int
    j_from_i: Pose
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class PoseGraphSolution:
    """Result of :func:`solve_pose_graph`.

    Attributes:
        poses: the N optimised ``cam_from_world`` poses.
        covariances: (N, 6, 6) marginal covariances in the node tangent space ``(ω, δc)``.
        cost: final ``½ Σ ‖whitened residual‖²``.
        evaluations: residual evaluations used by the solver.
    """

    poses: list[Pose]
    covariances: np.ndarray
    cost: float
    evaluations: int


class _Packed:
    """Factors as stacked arrays for vectorised residuals and Jacobians."""

    def __init__(
        self, n: int, absolute: Sequence[AbsoluteFactor], relative: Sequence[RelativeFactor]
    ) -> None:
        for a in absolute:
            if not 0 <= a.node < n:
                raise InputError(f"AbsoluteFactor.node {a.node} is not a node index (0..{n - 1})")
        for r in relative:
            if not (0 <= r.i < n and 0 <= r.j < n) or r.i == r.j:
                raise InputError(
                    f"RelativeFactor ({r.i}, {r.j}): need two different node indices in 0..{n - 1}"
                )
        self.n = n
        self.a_idx = np.array([f.node for f in absolute], dtype=np.int64)
        self.a_R = np.array([f.pose.R for f in absolute]).reshape(-1, 3, 3)
        self.a_c = np.array([f.pose.center for f in absolute]).reshape(-1, 3)
        self.a_U = np.array([_whitener("AbsoluteFactor.covariance", f.covariance) for f in absolute]).reshape(
            -1, 6, 6
        )
        self.r_i = np.array([f.i for f in relative], dtype=np.int64)
        self.r_j = np.array([f.j for f in relative], dtype=np.int64)
        self.r_R = np.array([f.j_from_i.R for f in relative]).reshape(-1, 3, 3)
        self.r_d = np.array([f.j_from_i.inverse().t for f in relative]).reshape(-1, 3)
        self.r_U = np.array([_whitener("RelativeFactor.covariance", f.covariance) for f in relative]).reshape(
            -1, 6, 6
        )
        self.m = 6 * (len(absolute) + len(relative))

    def residuals(self, R: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened residuals (m,), and the rotation errors of absolute and relative factors."""
        phi_a = (
            so3_log(R[self.a_idx] @ np.transpose(self.a_R, (0, 2, 1)))
            if len(self.a_idx)
            else np.zeros((0, 3))
        )
        ra = np.concatenate([phi_a, c[self.a_idx] - self.a_c], axis=1)
        Ri, Rj = R[self.r_i], R[self.r_j]
        if len(self.r_i):
            phi_r = so3_log(Rj @ np.transpose(Ri, (0, 2, 1)) @ np.transpose(self.r_R, (0, 2, 1)))
            d = np.einsum("nij,nj->ni", Ri, c[self.r_j] - c[self.r_i])
        else:
            phi_r, d = np.zeros((0, 3)), np.zeros((0, 3))
        rr = np.concatenate([phi_r, d - self.r_d], axis=1)
        r = np.concatenate(
            [np.einsum("nij,nj->ni", self.a_U, ra).ravel(), np.einsum("nij,nj->ni", self.r_U, rr).ravel()]
        )
        return r, phi_a, phi_r

    def jacobian(self, R: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(m, 6N) whitened Jacobian w.r.t. the local perturbation ``(ω, δc)`` of each node."""
        _, phi_a, phi_r = self.residuals(R, c)
        J = np.zeros((self.m, 6 * self.n))
        na = len(self.a_idx)
        if na:
            blk = np.zeros((na, 6, 6))
            blk[:, :3, :3] = so3_left_jacobian_inverse(phi_a)
            blk[:, 3:, 3:] = np.eye(3)
            W = self.a_U @ blk
            rows = 6 * np.arange(na)[:, None, None] + np.arange(6)[None, :, None]
            J[rows, 6 * self.a_idx[:, None, None] + np.arange(6)[None, None, :]] = W
        if len(self.r_i):
            Ri, Rj = R[self.r_i], R[self.r_j]
            Jinv = so3_left_jacobian_inverse(phi_r)
            d = np.einsum("nij,nj->ni", Ri, c[self.r_j] - c[self.r_i])
            bi = np.zeros((len(Ri), 6, 6))
            bj = np.zeros((len(Ri), 6, 6))
            bi[:, :3, :3] = -Jinv @ Rj @ np.transpose(Ri, (0, 2, 1))
            bj[:, :3, :3] = Jinv
            bi[:, 3:, :3] = -skew(d)
            bi[:, 3:, 3:] = -Ri
            bj[:, 3:, 3:] = Ri
            Wi, Wj = self.r_U @ bi, self.r_U @ bj
            rows = 6 * (na + np.arange(len(Ri)))[:, None, None] + np.arange(6)[None, :, None]
            J[rows, 6 * self.r_i[:, None, None] + np.arange(6)[None, None, :]] = Wi
            J[rows, 6 * self.r_j[:, None, None] + np.arange(6)[None, None, :]] = Wj
        return J


def _unpack(poses: Sequence[Pose]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([p.R for p in poses]).reshape(-1, 3, 3), np.array([p.center for p in poses]).reshape(
        -1, 3
    )


def _retract(R0: np.ndarray, c0: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = x.reshape(-1, 6)
    return so3_exp(x[:, :3]) @ R0, c0 + x[:, 3:]


def _covariances(J: np.ndarray, n: int) -> np.ndarray:
    H = J.T @ J
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full((n, 6, 6), np.inf)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        return np.full((n, 6, 6), np.inf)
    return np.stack([cov[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] for k in range(n)])


def marginal_covariances(
    poses: Sequence[Pose], absolute: Sequence[AbsoluteFactor], relative: Sequence[RelativeFactor]
) -> np.ndarray:
    """(N, 6, 6) marginal covariances of the nodes linearised at ``poses`` (no optimisation).

    Used to predict: add a node at ``j_from_i @ pose_i`` with its relative factor and read its
    covariance. All inf when the graph is not anchored (no absolute factor).
    """
    packed = _Packed(len(poses), absolute, relative)
    R, c = _unpack(poses)
    return _covariances(packed.jacobian(R, c), len(poses))


def solve_pose_graph(
    initial: Sequence[Pose],
    absolute: Sequence[AbsoluteFactor],
    relative: Sequence[RelativeFactor],
    max_evaluations: int = 50,
) -> PoseGraphSolution:
    """Least-squares poses of all nodes given the factors.

    Args:
        initial: N initial ``cam_from_world`` poses (the linearisation point).
        absolute: fixes and priors; at least one is needed to anchor the graph.
        relative: motion factors.
        max_evaluations: residual evaluations at most (one per Levenberg-Marquardt step tried).

    Returns:
        :class:`PoseGraphSolution`.

    Raises:
        InputError: no nodes, no absolute factor, bad node indices or covariances.

    Example:
        >>> I6 = np.eye(6) * 1e-4
        >>> a = AbsoluteFactor(0, Pose.identity(), I6)
        >>> m = RelativeFactor(0, 1, Pose(np.eye(3), [0, 0, -1.0]), I6)   # 1 m forward
        >>> sol = solve_pose_graph([Pose.identity(), Pose.identity()], [a], [m])
        >>> np.round(sol.poses[1].center, 6).tolist()
        [0.0, 0.0, 1.0]
    """
    n = len(initial)
    if n == 0:
        raise InputError("solve_pose_graph: need at least one node")
    if not absolute:
        raise InputError("solve_pose_graph: need at least one absolute factor to anchor the graph")
    packed = _Packed(n, absolute, relative)
    R, c = _unpack(initial)
    r, _, _ = packed.residuals(R, c)
    cost, lam, evaluations = float(r @ r), 1e-4, 1
    J = packed.jacobian(R, c)
    while evaluations < max_evaluations:
        H, g = J.T @ J, J.T @ r
        try:
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
        except np.linalg.LinAlgError:
            break
        R1, c1 = _retract(R, c, step)
        r1, _, _ = packed.residuals(R1, c1)
        evaluations += 1
        cost1 = float(r1 @ r1)
        if cost1 <= cost:
            done = np.max(np.abs(step)) < 1e-7 or cost - cost1 <= 1e-10 * max(cost, 1.0)
            R, c, r, cost, lam = R1, c1, r1, cost1, max(lam / 10.0, 1e-9)
            J = packed.jacobian(R, c)
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    poses = [Pose.from_center(Rk, ck) for Rk, ck in zip(_orthonormalize(R), c)]
    return PoseGraphSolution(poses, _covariances(J, n), 0.5 * cost, evaluations)


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    D = np.ones((len(R), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[:, None, :]) @ Vt


def marginalize_first(
    poses: Sequence[Pose], absolute: Sequence[AbsoluteFactor], relative: Sequence[RelativeFactor]
) -> tuple[list[AbsoluteFactor], list[RelativeFactor]]:
    """Drop node 0 and replace the factors touching it by a prior on node 1 (Schur complement).

    Requires that node 0's relative factors all connect it to node 1 (a chain). The remaining
    factors are re-indexed (node k becomes k − 1).

    Returns:
        (absolute factors, relative factors) of the graph over nodes 1..N−1.
    """
    if len(poses) < 2:
        raise InputError("marginalize_first: need at least two nodes")
    touch_a = [f for f in absolute if f.node == 0]
    touch_r = [f for f in relative if 0 in (f.i, f.j)]
    if any({f.i, f.j} != {0, 1} for f in touch_r):
        raise InputError("marginalize_first: node 0 must only be linked to node 1")
    keep_a = [AbsoluteFactor(f.node - 1, f.pose, f.covariance) for f in absolute if f.node != 0]
    keep_r = [
        RelativeFactor(f.i - 1, f.j - 1, f.j_from_i, f.covariance) for f in relative if 0 not in (f.i, f.j)
    ]
    if touch_r and touch_a:
        packed = _Packed(2, [AbsoluteFactor(0, f.pose, f.covariance) for f in touch_a], touch_r)
        R, c = _unpack(poses[:2])
        J = packed.jacobian(R, c)
        H, b = J.T @ J, J.T @ packed.residuals(R, c)[0]
        try:
            info = H[6:, 6:] - H[6:, :6] @ np.linalg.solve(H[:6, :6], H[:6, 6:])
            info = 0.5 * (info + info.T)
            cov = np.linalg.inv(info)
            np.linalg.cholesky(cov)
            # the Gaussian's mean on node 1: the minimum of the marginalised factors (Schur on b too)
            shift = -cov @ (b[6:] - H[6:, :6] @ np.linalg.solve(H[:6, :6], b[:6]))
        except np.linalg.LinAlgError:
            cov = None
        if cov is not None:
            R1, c1 = _retract(R[1:2], c[1:2], shift)
            keep_a.insert(0, AbsoluteFactor(0, Pose.from_center(_orthonormalize(R1)[0], c1[0]), cov))
    return keep_a, keep_r
