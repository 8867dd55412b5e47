"""The stream's sliding window: one node per recent frame, the factors between them, and the
current node's marginal covariance (:class:`PoseWindow`).

A node (:class:`WindowNode`) is a frame's ``cam_from_world`` pose, its stamp, the motion that led
into it and whether an accepted fix anchors it. Factors are those of
:mod:`planarloc.robust.pose_graph`: absolute (fixes, poses from tracked map points, the prior a
marginalised node leaves) and relative (the motions). Covariances are in pose-graph order
(:mod:`planarloc.geometry.pose_covariance`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.localize.motion_model import Motion, VisualStep
from planarloc.robust.pose_graph import (
    AbsoluteFactor,
    RelativeFactor,
    marginal_covariances,
    marginalize_first,
    solve_pose_graph,
)


@dataclass
class WindowNode:
    """One frame in the window.

    Attributes:
        pose: its ``cam_from_world`` (the solved one, or the prediction).
        stamp: its time (s).
        source: the motion into it (:attr:`Motion.source`; ``"none"`` for a start).
        visual: the visual step of that motion, while it may be scaled again.
        fixed: an accepted fix anchors it.
    """

    pose: Pose
    stamp: float
    source: str = "none"
    visual: VisualStep | None = None
    fixed: bool = False


@dataclass(frozen=True)
class Alternative:
    """The window with one motion replaced (:meth:`PoseWindow.with_motion`), not yet adopted."""

    node: int
    poses: list[Pose]
    relative: list[RelativeFactor]
    covariance: np.ndarray  # the marginal covariance of ``node`` under it
    source: str


class PoseWindow:
    """Nodes, factors and the current node's covariance (module docstring).

    Args:
        size: nodes kept; older ones are marginalised (:meth:`drop_oldest`).
    """

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self.clear()

    def clear(self) -> None:
        self.nodes: list[WindowNode] = []
        self.absolute: list[AbsoluteFactor] = []
        self.relative: list[RelativeFactor] = []
        self.covariance = np.full((6, 6), np.inf)  # of the current node
        self.exact = True  # ``covariance`` is the marginal, not a guess
        self.dirty = False  # a factor was added since the last solve

    # ---- reading --------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.nodes)

    @property
    def poses(self) -> list[Pose]:
        return [n.pose for n in self.nodes]

    @property
    def current(self) -> WindowNode:
        return self.nodes[-1]

    def node_at(self, stamp: float) -> int | None:
        """The index of the node of ``stamp``, None when it left the window."""
        for k in range(len(self.nodes) - 1, -1, -1):
            if self.nodes[k].stamp == stamp:
                return k
        return None

    def last_fixed(self) -> int | None:
        """The latest node an accepted fix anchors."""
        return max((k for k, n in enumerate(self.nodes) if n.fixed), default=None)

    def last_absolute(self) -> int:
        """The latest node with an absolute factor (-1: none)."""
        return max((f.node for f in self.absolute), default=-1)

    def anchored_nodes(self) -> list[int]:
        """The nodes with an absolute factor, in order."""
        return sorted({f.node for f in self.absolute})

    def absolute_at(self, node: int) -> bool:
        return any(f.node == node for f in self.absolute)

    def sources_after(self, node: int) -> list[str]:
        return [n.source for n in self.nodes[node + 1 :]]

    def last_step(self, node: int) -> Pose | None:
        """``cur_from_prev`` of the nodes ``node − 1`` → ``node`` (None before the second node)."""
        if node < 1:
            return None
        return self.nodes[node].pose @ self.nodes[node - 1].pose.inverse()

    # ---- changing -------------------------------------------------------------------------
    def start(self, pose: Pose, covariance: np.ndarray, stamp: float) -> None:
        """A window of one fixed node."""
        self.clear()
        self.nodes = [WindowNode(pose, stamp, fixed=True)]
        self.absolute = [AbsoluteFactor(0, pose, covariance)]
        self.covariance = covariance

    def append(self, motion: Motion, stamp: float) -> None:
        """A new node predicted by ``motion`` from the last one. Until the window is solved or
        marginalised again (:meth:`refresh`), its covariance is the last one grown by the
        motion's without cross terms (for gating only)."""
        n = len(self.nodes)
        prev = self.nodes[-1].pose
        self.nodes.append(WindowNode(motion.cur_from_prev @ prev, stamp, motion.source, motion.visual))
        self.relative.append(RelativeFactor(n - 1, n, motion.cur_from_prev, motion.covariance))
        cov = self.covariance.copy()
        R = prev.R.T
        cov[:3, :3] += motion.covariance[:3, :3]
        cov[3:, 3:] += R @ motion.covariance[3:, 3:] @ R.T
        self.covariance, self.exact = cov, False

    def add_absolute(self, node: int, pose: Pose, covariance: np.ndarray) -> None:
        self.absolute.append(AbsoluteFactor(node, pose, covariance))
        self.dirty = True

    def solve(self) -> None:
        """Solve the window for its poses and the current node's covariance."""
        sol = solve_pose_graph(self.poses, self.absolute, self.relative)
        for node, pose in zip(self.nodes, sol.poses):
            node.pose = pose
        self.covariance, self.exact, self.dirty = sol.covariances[-1], True, False

    def marginalize(self) -> None:
        """The current node's exact marginal covariance without solving."""
        if self.nodes:
            self.covariance = marginal_covariances(self.poses, self.absolute, self.relative)[-1]
            self.exact = True

    def drop_oldest(self) -> None:
        """Marginalise the oldest node into a prior on the next one."""
        absolute, relative = marginalize_first(self.poses, self.absolute, self.relative)
        if not absolute:  # nothing anchored the oldest node: keep the current marginal as a prior
            cov = marginal_covariances(self.poses, self.absolute, self.relative)[1]
            absolute = [AbsoluteFactor(0, self.nodes[1].pose, cov)]
        self.absolute, self.relative = absolute, relative
        self.nodes = self.nodes[1:]

    def with_motion(self, node: int, motion: Motion) -> Alternative:
        """The window with the motion into ``node`` replaced by ``motion`` (later nodes keep their
        guesses), and ``node``'s marginal covariance under it."""
        relative = [
            f
            if not (f.j == node and f.i == node - 1)
            else RelativeFactor(node - 1, node, motion.cur_from_prev, motion.covariance)
            for f in self.relative
        ]
        poses = self.poses
        poses[node] = motion.cur_from_prev @ poses[node - 1]
        cov = marginal_covariances(poses, self.absolute, relative)[node]
        return Alternative(node, poses, relative, cov, motion.source)

    def adopt(self, alt: Alternative, source: str) -> None:
        """Take an :class:`Alternative`; the replaced node's motion source becomes ``source``."""
        for n, pose in zip(self.nodes, alt.poses):
            n.pose = pose
        self.relative = alt.relative
        self.nodes[alt.node].source, self.nodes[alt.node].visual = source, None
        if alt.node == len(self.nodes) - 1:
            self.covariance = alt.covariance

    def rechain(self, start: int) -> None:
        """Initial guesses of the nodes after ``start`` from their motions (before a solve)."""
        for f in sorted(self.relative, key=lambda f: f.j):
            if f.j > start and f.j == f.i + 1:
                self.nodes[f.j].pose = f.j_from_i @ self.nodes[f.i].pose

    def restart_at(self, node: int, pose: Pose, covariance: np.ndarray) -> None:
        """Restart the window at ``node`` from ``pose`` (a confirmed kidnap), keeping the motions
        measured since (the nodes after it are chained from it again)."""
        kept = self.nodes[node:]
        relative = [
            RelativeFactor(f.i - node, f.j - node, f.j_from_i, f.covariance)
            for f in self.relative
            if f.i >= node
        ]
        self.start(pose, covariance, kept[0].stamp)
        self.nodes += [replace(n, fixed=False) for n in kept[1:]]
        self.relative = relative
        self.dirty = bool(relative)

    def anchor_stamp(self, node: int) -> float:
        """The stamp of the latest node at or before ``node`` with an absolute factor (the
        window's first node, whose prior anchors it, when none has)."""
        anchored = [f.node for f in self.absolute if f.node <= node]
        return self.nodes[max(anchored, default=0)].stamp

    def rescale(self, motion: Callable[[VisualStep], Motion]) -> None:
        """Scale the visual motions again (``motion``: a visual step to its motion now), each
        chained from the latest absolute pose before it as the window now holds them."""
        for k, f in enumerate(self.relative):
            n = self.nodes[f.j]
            if f.j == f.i + 1 and n.source == "visual" and n.visual is not None:
                n.visual = replace(n.visual, since_anchor_s=self.nodes[f.i].stamp - self.anchor_stamp(f.i))
                m = motion(n.visual)
                self.relative[k] = RelativeFactor(f.i, f.j, m.cur_from_prev, m.covariance)

    def carried(
        self,
        pose: Pose,
        covariance: np.ndarray,
        prev: int,
        node: int,
        weak: Callable[[int, float], np.ndarray],
    ) -> tuple[Pose, np.ndarray]:
        """A pose estimate of node ``prev`` moved to node ``node`` through the window's motion
        between them, its covariance grown by those motions' and, where the motion was not
        wheel odometry, by ``weak(i, dt)`` (the weak constant-velocity model's from node ``i``:
        visual odometry may be wrong exactly across a kidnap)."""
        moved = (self.nodes[node].pose @ self.nodes[prev].pose.inverse()) @ pose
        motion_cov = np.zeros((6, 6))
        for f in self.relative:
            if prev < f.j <= node:
                motion_cov += f.covariance
                if self.nodes[f.j].source != "odometry":
                    motion_cov += weak(f.i, self.nodes[f.j].stamp - self.nodes[f.i].stamp)
        R = pose.R.T
        motion_cov[3:, 3:] = R @ motion_cov[3:, 3:] @ R.T
        return moved, covariance + motion_cov
