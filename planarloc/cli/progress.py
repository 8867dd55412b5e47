"""Progress on stderr: a bar per stage on a terminal, plain lines everywhere else.

Without a terminal (a container image build, CI, a pipe) a bar would show nothing until the end;
:func:`progress_reporter` then prints one line when a stage starts, at most one every
``interval`` seconds while it runs, and one when it completes, e.g.::

    compile kernels: 0/41 (0 s)
    compile kernels: 17/41 (10 s)
    compile kernels: 41/41, done in 31 s

Elapsed times run from the first report of a stage (callers report ``done = 0`` when a stage
starts, so that its time includes the first item). Library code receives the plain callback
``update(stage, done, total)``; the callback may be called from several threads.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

Update = Callable[[str, int, int], None]
#: Seconds between two plain progress lines of one stage.
LINE_INTERVAL = 10.0


@contextmanager
def progress_reporter(console: Console, interval: float = LINE_INTERVAL) -> Iterator[Update]:
    """Yield ``update(stage, done, total)``: a rich bar per stage on a terminal, else plain lines."""
    if console.is_terminal:
        with _bars(console) as update:
            yield update
    else:
        yield _Lines(console, interval)


@contextmanager
def _bars(console: Console) -> Iterator[Update]:
    with Progress(
        TextColumn("[bold]{task.description:<16}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as prog:
        tasks: dict[str, TaskID] = {}
        lock = threading.Lock()

        def update(stage: str, done: int, total: int) -> None:
            with lock:
                if stage not in tasks:
                    tasks[stage] = prog.add_task(stage, total=total)
                prog.update(tasks[stage], completed=done, total=total)

        yield update


class _Lines:
    """The plain-line reporter (see the module docstring)."""

    def __init__(self, console: Console, interval: float) -> None:
        self._console = console
        self._interval = interval
        self._lock = threading.Lock()
        self._started: dict[str, float] = {}
        self._last: dict[str, float] = {}
        self._finished: set[str] = set()

    def __call__(self, stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        with self._lock:
            if stage in self._finished:
                return
            first = stage not in self._started
            if first:
                self._started[stage] = self._last[stage] = now
            elapsed = now - self._started[stage]
            if done >= total:
                self._finished.add(stage)
                line = f"{stage}: {done}/{total}, done in {elapsed:.0f} s"
            elif first or now - self._last[stage] >= self._interval:
                line = f"{stage}: {done}/{total} ({elapsed:.0f} s)"
            else:
                return
            self._last[stage] = now
            self._console.print(line, markup=False, highlight=False)
