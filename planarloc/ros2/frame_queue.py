"""The node's bookkeeping of camera frames: the queue of frames waiting for the worker
(:class:`FrameQueue`) and what became of the frames received (:class:`FrameCounts`)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

from planarloc.geometry.validation import InputError


class FrameQueue:
    """The frames waiting for the node's worker, oldest first, at most ``size`` (not thread-safe:
    the node holds its lock).

    :meth:`push` drops the oldest waiting frame when full; :meth:`restart` (an ``/initialpose``)
    marks the next frame pushed as the first of a new stream, and a restart survives the drop
    of its frame (it moves to the next one).
    """

    def __init__(self, size: int) -> None:
        if size < 1:
            raise InputError(f"queue_size: expected an integer >= 1, got {size}")
        self.size = size
        self._items: deque[tuple[Any, float, bool]] = deque()  # frame, arrival time, restart before it
        self._restart = False

    def __len__(self) -> int:
        return len(self._items)

    def restart(self) -> None:
        self._restart = True

    def push(self, frame: Any, arrival: float) -> int:
        """Queue ``frame``; returns how many frames were dropped to make room (0 or 1)."""
        restart, self._restart = self._restart, False
        dropped = 0
        if len(self._items) >= self.size:
            _, _, carried = self._items.popleft()
            dropped = 1
            if carried and self._items:
                self._items[0] = (*self._items[0][:2], True)
            restart = restart or (carried and not self._items)
        self._items.append((frame, arrival, restart))
        return dropped

    def pop(self) -> tuple[Any, float, bool]:
        """The oldest frame: ``(frame, arrival time, restart the stream before it)``."""
        return self._items.popleft()


@dataclass
class FrameCounts:
    """What the node has done with the frames it received."""

    received: int = 0
    processed: int = 0
    dropped: int = 0  # replaced by a newer frame before the worker took it
    failed: int = 0  # not localizable: no CameraInfo yet, a bad image or camera
    localized: int = 0
    predicted: int = 0
    lost: int = 0
    published: int = 0

    @property
    def fix_rate(self) -> float:
        """Share of the processed frames that were localized."""
        return self.localized / self.processed if self.processed else 0.0
