"""Pose samples of ROS bags (:mod:`planarloc.io.rosbag`): pose samples that share a stamp, and the
``/tf`` + ``/tf_static`` buffer that chains transforms from a parent frame down to a child frame."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.io.format_error import FormatError
from planarloc.io.ros_messages import transform_edge
from planarloc.io.rosbag_messages import _stamp_ns, at_stamp
from planarloc.io.tum import associate_timestamps

logger = logging.getLogger("planarloc.io.rosbag")  # the bag reader's logger (its warnings keep their source)


def _same_pose(a: Pose, b: Pose, tol: float = 1e-9) -> bool:
    return bool(np.allclose(a.matrix, b.matrix, atol=tol))


def distinct_samples(
    times: Sequence[float], poses: Sequence[Pose], what: str
) -> tuple[list[float], list[Pose]]:
    """The pose samples of one source (a pose topic, a ``/tf`` edge) without ambiguous stamps:
    samples sharing a stamp count once if their poses agree, else all of them are dropped with a
    warning per message (a frame at that time cannot be given the right one)."""
    by_stamp: dict[float, list[int]] = {}
    for i, t in enumerate(times):
        by_stamp.setdefault(float(t), []).append(i)
    keep = []
    for t, idx in by_stamp.items():
        if len(idx) == 1 or all(_same_pose(poses[idx[0]], poses[i]) for i in idx[1:]):
            keep.append(idx[0])
            continue
        for i in idx:
            logger.warning(
                "%s: %d pose samples share this stamp with different poses; none of them is used",
                at_stamp(what, int(round(t * 1e9))),
                len(idx),
            )
    keep.sort()
    return [float(times[i]) for i in keep], [poses[i] for i in keep]


class TfBuffer:
    """Static and time-stamped transforms ``parent_from_child`` per edge (child -> parent)."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, Pose]] = {}
        self.dynamic: dict[str, tuple[str, list[float], list[Pose]]] = {}

    def add(self, msg: Any, static: bool, bag_ns: int = 0) -> None:
        for tf in msg.transforms:
            parent, child, pose = transform_edge(tf)
            if static:
                if child in self.static and not _same_pose(self.static[child][1], pose):
                    logger.warning(
                        "/tf_static: %s -> %s is published twice with different transforms; the later "
                        "is used",
                        parent,
                        child,
                    )
                self.static[child] = (parent, pose)
            else:
                entry = self.dynamic.setdefault(child, (parent, [], []))
                entry[1].append(_stamp_ns(tf, bag_ns) * 1e-9)
                entry[2].append(pose)

    def parent(self, child: str) -> str | None:
        if child in self.static:
            return self.static[child][0]
        if child in self.dynamic:
            return self.dynamic[child][0]
        return None

    def chain(self, parent: str, child: str) -> list[str] | None:
        """Frames from ``child`` up to (excluding) ``parent``, or None if ``parent`` is not an ancestor."""
        out: list[str] = []
        frame = child
        while frame != parent:
            out.append(frame)
            up = self.parent(frame)
            if up is None or len(out) > 1000:
                return None
            frame = up
        return out

    def static_chain(self, parent: str, child: str) -> Pose | None:
        """``parent_from_child`` if ``child`` hangs below ``parent`` through static transforms only."""
        chain = self.chain(parent, child)
        if chain is None or any(f not in self.static for f in chain):
            return None
        pose = Pose.identity()
        for f in chain:
            pose = self.static[f][1] @ pose
        return pose

    def frames(self) -> list[str]:
        names = set(self.static) | set(self.dynamic)
        names |= {p for p, _ in self.static.values()} | {e[0] for e in self.dynamic.values()}
        return sorted(names)

    def poses_at(
        self, parent: str, child: str, times: np.ndarray, max_dt: float, root: Path
    ) -> list[Pose | None]:
        """``parent_from_child`` at each time (None where a dynamic edge has no sample within max_dt)."""
        chain = self.chain(parent, child)
        if chain is None:
            raise FormatError(
                root,
                None,
                f"tf_parent={parent!r} is not an ancestor of tf_child={child!r} in /tf and /tf_static "
                f"(frames: {', '.join(self.frames()) or 'none'})",
            )
        out: list[Pose | None] = [Pose.identity() for _ in times]
        for frame in chain:
            if frame in self.static:
                edge = self.static[frame][1]
                out = [None if p is None else edge @ p for p in out]
                continue
            parent, stamps, poses = self.dynamic[frame]
            stamps, poses = distinct_samples(stamps, poses, f"/tf {parent} -> {frame}")
            idx = associate_timestamps(times, stamps, max_dt)
            out = [None if p is None or i < 0 else poses[i] @ p for p, i in zip(out, idx)]
        return out
