"""A stream's stamps: checked to come in order, and gaps that tell missing frames."""

from __future__ import annotations

from collections import deque

import numpy as np

from planarloc.geometry.validation import InputError

#: recent frame periods used to tell missing frames
PERIODS_KEPT = 9


class StreamClock:
    """The stamps of a stream's frames so far.

    :meth:`check` refuses a stamp that is not a finite time after the last one; :meth:`missing`
    counts the frames a gap of more than 1.5 recent median periods stands for.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.last: float | None = None
        self._periods: deque[float] = deque(maxlen=PERIODS_KEPT)

    def check(self, stamp: object) -> float:
        """``stamp`` as seconds; InputError when it is not a finite time after the last frame's."""
        try:
            t = float(stamp)  # type: ignore[arg-type]  # any object: float() decides, TypeError handled
        except (TypeError, ValueError):
            raise InputError(f"stamp: expected a time in seconds, got {stamp!r}") from None
        if not np.isfinite(t):
            raise InputError(f"stamp: expected a finite time in seconds, got {t}")
        if self.last is not None and t <= self.last:
            what = "the same as" if t == self.last else "before"
            raise InputError(
                f"stamp {t:.6f}: {what} the previous frame's {self.last:.6f}; frames must come in "
                "time order, each once (reset() starts a new stream)"
            )
        return t

    def advance(self, stamp: float) -> int:
        """Take the (checked) stamp of the next frame; returns the frames missing before it."""
        last, self.last = self.last, stamp
        if last is None:
            return 0
        dt = stamp - last
        period = float(np.median(self._periods)) if len(self._periods) >= 3 else None
        self._periods.append(dt)
        if period is None or dt <= 1.5 * period:
            return 0
        return max(int(round(dt / period)) - 1, 1)
