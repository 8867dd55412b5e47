"""Recording numba's compilations of planarloc's kernels (numba's ``numba:compile`` events)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numba is imported when recording starts
    from numba.core.event import Listener


class CompileRecorder:
    """Records numba's compile events while registered: for each planarloc kernel compiled
    (called from Python or from another kernel), the CPU seconds of each signature's compilation
    without the planarloc kernels it compiled on the way (numba's own overloads count for the
    kernel that needed them). Use as a context manager.

    Attributes:
        kernels: ``module:qualname`` -> signature repr -> CPU seconds.
        overloads: numba's own functions compiled for a planarloc kernel -> CPU seconds.
    """

    def __init__(self) -> None:
        self.kernels: dict[str, dict[str, float]] = {}
        self.overloads: dict[str, float] = {}
        self._stack: list[list] = []
        self._listener: Listener | None = None

    def _start(self, data: dict) -> None:
        self._stack.append([data["dispatcher"], data["args"], time.process_time(), 0.0])

    def _end(self) -> None:
        d, sig, t0, inner = self._stack.pop()
        total = time.process_time() - t0
        mine = d.py_func.__module__.startswith("planarloc.")
        key = f"{d.py_func.__module__}:{d.py_func.__qualname__}"
        if mine:
            sigs = self.kernels.setdefault(key, {})
            text = repr(tuple(sig))
            sigs[text] = sigs.get(text, 0.0) + total - inner
        elif self._stack and self._stack[-1][0].py_func.__module__.startswith("planarloc."):
            self.overloads[key] = self.overloads.get(key, 0.0) + total - inner
        if self._stack and mine:
            self._stack[-1][3] += total

    def __enter__(self) -> CompileRecorder:
        from numba.core import event

        recorder = self

        class Listener(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                recorder._start(ev.data)

            def on_end(self, ev: event.Event) -> None:
                recorder._end()

        self._listener = Listener()
        event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc: object) -> None:
        from numba.core import event

        event.unregister("numba:compile", self._listener)

    def manifest_entries(self) -> dict[str, dict]:
        """``{kernel: {"signatures": [...], "compile_s": seconds}}``, as in ``kernels.json``."""
        return {
            k: {"signatures": list(sigs), "compile_s": sum(sigs.values())} for k, sigs in self.kernels.items()
        }
