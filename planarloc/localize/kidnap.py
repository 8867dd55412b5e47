"""Kidnap detection for a stream: rejected global fixes that agree with each other.

A single fix that contradicts the prediction is more likely wrong than the robot moved without
the stream seeing it. ``SequenceConfig.kidnap_confirmations`` consecutive rejected global fixes
that agree with each other — each carried to the next one's frame through the window's motion
(:meth:`planarloc.localize.pose_window.PoseWindow.carried`) — confirm a kidnap, and the stream
restarts from the latest of them. With no measured motion since the last accepted fix, one
rejected global fix already makes the stream **doubt** its pose: it has nothing that says the
robot did not move there. So does a **view break**: a frame whose corners were tracked but whose
tracks fit no relative pose (the scene changed more than any motion explains, as when a robot is
carried away), until a fix of that frame or a later one is accepted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.localize.fixes import mahalanobis_sq


@dataclass(frozen=True)
class KidnapCandidate:
    """A rejected global fix waiting for confirmation: its pose and covariance at the node of
    frame ``stamp``, and how many consecutive agreeing fixes it stands for."""

    pose: Pose
    covariance: np.ndarray
    count: int
    stamp: float


class KidnapMonitor:
    """The candidate kidnap and the stream's doubt (module docstring).

    Args:
        gate: the χ²(6) threshold two fixes must pass to agree.
        confirmations: agreeing fixes that confirm a kidnap.
    """

    def __init__(self, gate: float, confirmations: int) -> None:
        self.gate, self.confirmations = float(gate), int(confirmations)
        self.clear()

    def clear(self) -> None:
        """A restart: nothing is suspected."""
        self.candidate: KidnapCandidate | None = None
        self.doubt = False
        self.view_break: float | None = None

    def accept(self, stamp: float) -> None:
        """A fix of frame ``stamp`` was accepted: the candidate and the doubt go; a view break
        goes only when the fix is of a frame at or after it (an older frame's fix says nothing
        about where the robot went since)."""
        self.candidate, self.doubt = None, False
        if self.view_break is not None and stamp >= self.view_break:
            self.view_break = None

    def broke_view(self, stamp: float) -> None:
        """The view changed more than any motion explains at frame ``stamp`` (the tracks found no
        relative pose although they found the corners): the robot may have been carried away."""
        self.view_break = stamp

    @property
    def doubted(self) -> bool:
        """The stream has no pose it can vouch for until a fix settles it."""
        return self.doubt or self.view_break is not None

    @property
    def suspected(self) -> bool:
        return self.candidate is not None

    def consider(
        self,
        pose: Pose,
        covariance: np.ndarray,
        stamp: float,
        carry: Callable[[KidnapCandidate], tuple[Pose, np.ndarray] | None],
    ) -> None:
        """A rejected global fix of frame ``stamp``: it confirms the candidate when the candidate,
        carried to its frame (``carry``; None when the candidate's frame is not before it),
        agrees with it; else it becomes the candidate."""
        c = self.candidate
        if c is not None:
            carried = carry(c)
            if carried is not None and mahalanobis_sq(pose, covariance, *carried) <= self.gate:
                self.candidate = KidnapCandidate(pose, covariance, c.count + 1, stamp)
                return
        self.candidate = KidnapCandidate(pose, covariance, 1, stamp)

    def confirmed(self) -> KidnapCandidate | None:
        """The candidate once enough fixes agree with it."""
        c = self.candidate
        return c if c is not None and c.count >= self.confirmations else None

    def moved(self, old_stamp: float, pose: Pose, covariance: np.ndarray, stamp: float) -> None:
        """The candidate's node leaves the window: it is carried to the next one (``pose``,
        ``covariance`` at frame ``stamp``), so that a fix result that comes later still meets it."""
        c = self.candidate
        if c is not None and c.stamp == old_stamp:
            self.candidate = KidnapCandidate(pose, covariance, c.count, stamp)
