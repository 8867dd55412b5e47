"""The node's frame queue: bounded, oldest dropped first and counted, restarts never lost."""

from __future__ import annotations

import pytest

from planarloc.geometry.validation import InputError
from planarloc.ros2.node import FrameQueue, NodeSettings


def test_a_slow_step_is_absorbed_up_to_the_size_then_the_oldest_frames_go() -> None:
    q = FrameQueue(3)
    dropped = [q.push(f"frame{i}", float(i)) for i in range(5)]
    assert dropped == [0, 0, 0, 1, 1]
    assert [q.pop()[0] for _ in range(len(q))] == ["frame2", "frame3", "frame4"]


def test_size_one_keeps_only_the_newest_frame() -> None:
    q = FrameQueue(1)
    assert q.push("a", 0.0) == 0 and q.push("b", 0.1) == 1
    assert len(q) == 1 and q.pop() == ("b", 0.1, False)


def test_a_restart_applies_to_the_next_frame_and_survives_its_drop() -> None:
    q = FrameQueue(2)
    q.push("before", 0.0)
    q.restart()
    q.push("after", 0.1)
    assert [q.pop() for _ in range(2)] == [("before", 0.0, False), ("after", 0.1, True)]
    q.push("before", 0.0)
    q.restart()
    q.push("after", 0.1)
    q.push("later", 0.2)  # drops "before": the restart stays on "after"
    q.push("latest", 0.3)  # drops "after": the restart moves to "later"
    assert [q.pop() for _ in range(2)] == [("later", 0.2, True), ("latest", 0.3, False)]
    q = FrameQueue(1)
    q.restart()
    q.push("x", 0.0)
    q.push("y", 0.1)  # the only frame carrying the restart is dropped
    assert q.pop() == ("y", 0.1, True)


def test_bad_queue_sizes_are_one_line_errors() -> None:
    with pytest.raises(InputError, match="queue_size"):
        FrameQueue(0)
    with pytest.raises(InputError, match="parameter queue_size"):
        NodeSettings(map="m.db", queue_size=0)
