"""A first use on an empty kernel cache without waiting for the compile: the kernels run as Python
(:mod:`.interpreted`) while a detached process compiles them (:mod:`.background`), until it ends.

:func:`start_first_use` is what a front door calls before its first query (``planarloc
localize``, the ROS 2 node): None when every kernel of its warm-up steps is cached (or cannot be
kept: then they compile on first use, as before); else a :class:`FirstUse` whose ``notice`` the
front door says once and whose :meth:`FirstUse.poll` it calls between queries. ``end`` returns to
compiled kernels in any case (the front door's exit). The processes of a pool (the service's
workers) share one compile: :func:`first_use_in_pool`.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from planarloc.compile.ahead import compile_ahead, plan_ahead
from planarloc.compile.background import BackgroundCompile, compile_in_background
from planarloc.compile.interpreted import PythonKernels

__all__ = [
    "COMPILE_CHOICES",
    "COMPILE_ENV",
    "FirstUse",
    "compile_setting",
    "first_use_in_pool",
    "first_use_or_compile",
    "start_first_use",
]

#: The environment variable that chooses how a front door treats an empty kernel cache:
#: ``wait`` compiles on every core first; ``auto`` (the default) and ``background`` run as
#: Python meanwhile (``planarloc localize --compile``: ``auto`` waits for more than 12 queries).
COMPILE_ENV = "PLANARLOC_COMPILE"
COMPILE_CHOICES = ("auto", "background", "wait")

logger = logging.getLogger(__name__)


@dataclass
class FirstUse:
    """Kernels run as Python while ``compiling`` (a detached compile of ``missing`` kernels) runs."""

    compiling: BackgroundCompile
    kernels: PythonKernels
    missing: int

    @property
    def notice(self) -> str:
        """The one line that says what happens, and how to avoid it."""
        who = (
            "compiling them in the background" if self.compiling.ours else "another command is compiling them"
        )
        return (
            f"planarloc's kernels are not compiled yet ({self.missing} kernels): {who} "
            f"(pid {self.compiling.pid or 'not yet known'}, log {self.compiling.log}); until it ends, "
            "queries run as Python, slower. `planarloc warmup` at install or image-build time compiles "
            f"them ahead; {COMPILE_ENV}=wait compiles them first"
        )

    @property
    def as_python(self) -> bool:
        """Whether the kernels still run as Python."""
        return self.kernels.active

    def poll(self) -> bool:
        """Between queries: once the compile has ended, return to compiled kernels. Returns True
        exactly once, when that happens now."""
        if self.kernels.active and self.compiling.done():
            self.kernels.end()
            return True
        return False

    def end(self) -> None:
        """Compiled kernels from now on (those the compile missed compile on first use)."""
        self.kernels.end()


def compile_setting() -> str:
    """``$PLANARLOC_COMPILE`` (default ``auto``).

    Raises:
        ValueError: a value not in :data:`COMPILE_CHOICES` (one line naming the variable).
    """
    value = os.environ.get(COMPILE_ENV, "auto")
    if value not in COMPILE_CHOICES:
        raise ValueError(f"{COMPILE_ENV}={value!r}: expected one of {', '.join(COMPILE_CHOICES)}")
    return value


def start_first_use(steps: Sequence[str], jobs: int | None = None) -> FirstUse | None:
    """If kernels of the warm-up ``steps`` miss the cache: start (or join) their compile in the
    background on ``jobs`` cores (default: all but one, left to the queries) and run the kernels
    as Python until it ends. None when nothing is to be compiled.

    Raises:
        OSError: the compile cannot be started (no writable temp folder for its lock and log);
            the caller compiles otherwise (``compile_ahead``) or lazily.
    """
    plan = plan_ahead(steps, jobs)
    if plan is None:
        return None
    compiling = compile_in_background(steps, jobs=jobs or max(1, plan.jobs - 1))
    return FirstUse(compiling, PythonKernels(), len(plan.missing))


def first_use_or_compile(
    steps: Sequence[str],
    say: Callable[[str], None],
    wait: bool,
    compile_first: Callable[[Sequence[str]], object] | None = None,
) -> FirstUse | None:
    """What a front door does before its first query (``planarloc localize``, the ROS 2 node):
    unless ``wait``, :func:`start_first_use` (its notice to ``say``); with ``wait``, or when the
    compile cannot be started (said), compile the missing kernels on every core first:
    ``compile_first(steps)`` (default :func:`compile_ahead`, its notice to ``say``; the command
    line passes its own, with a progress bar). The caller polls and ends the returned
    :class:`FirstUse`, if any."""
    if not wait:
        try:
            first = start_first_use(steps)
        except OSError as exc:
            say(f"cannot compile planarloc's kernels in the background ({exc}); compiling them first")
        else:
            if first is not None:
                say(first.notice)
            return first
    if compile_first is None:
        compile_ahead(steps, notify=say)
    else:
        compile_first(steps)
    return None


#: How often a pool's process that waits for the shared compile looks whether it has ended (s).
POOL_WAIT_POLL_S = 0.5


def first_use_in_pool(steps: Sequence[str], say: Callable[[str], None], wait: bool) -> FirstUse | None:
    """What each process of a pool does before its first query (``planarloc serve``'s workers, a
    Ray Serve replica): the processes share one detached compile, whichever starts it first (the
    others join it), so a cold pool of N workers compiles once, not N times on one core each
    inside their first requests (``planarloc serve`` on an empty cache, 2 workers on 2 cores:
    96 s for each worker's first request, against a job timeout of 120 s).

    Without ``wait`` the process runs its kernels as Python meanwhile (:func:`start_first_use`;
    the notice to ``say``; the caller polls and ends the returned :class:`FirstUse`). With
    ``wait`` the compile runs on every core and the process waits for its end before it returns
    None: the pool answers compiled from its first request. When the compile cannot be started
    (said), the kernels compile on first use, in each process, as before.
    """
    try:
        first = start_first_use(steps, jobs=(os.cpu_count() or 1) if wait else None)
    except OSError as exc:
        say(f"cannot compile planarloc's kernels in the background ({exc}); they compile on first use")
        return None
    if first is None:
        return None
    if not wait:
        say(first.notice)
        return first
    say(
        f"planarloc's kernels are not compiled yet ({first.missing} kernels): waiting for their "
        f"compile (pid {first.compiling.pid or 'not yet known'}, log {first.compiling.log}) "
        f"before the first query ({COMPILE_ENV}=wait)"
    )
    while not first.compiling.done():
        time.sleep(POOL_WAIT_POLL_S)
    first.end()
    return None
