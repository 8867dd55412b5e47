"""Compiling ahead, before a command or a service estimates poses: when kernels the coming
queries use are not in numba's cache, compile them on every core first (:mod:`.schedule`).

Compiling ahead is only a speed-up: with a kernel list that cannot be read (one warning) or a
cache that cannot keep kernels (the kernel cache says so), nothing is done and the kernels
compile on first use. :func:`compile_lazily` switches it off on purpose (profiling a cold first
use: every kernel then compiles in the process that calls it).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

from planarloc.compile.cache import kernels_persist, missing_kernels
from planarloc.compile.manifest import Manifest, ManifestError, load_manifest
from planarloc.compile.schedule import CompileReport, compile_kernels, estimated_seconds
from planarloc.compile.steps import Update

logger = logging.getLogger(__name__)

_lazy = {"depth": 0}
_lazy_lock = threading.Lock()


@contextmanager
def compile_lazily() -> Iterator[None]:
    """Within: :func:`plan_ahead` plans nothing, so every kernel compiles lazily where it is called
    (``benchmarks/compile_profile.py`` records those compilations)."""
    with _lazy_lock:
        _lazy["depth"] += 1
    try:
        yield
    finally:
        with _lazy_lock:
            _lazy["depth"] -= 1


@dataclass(frozen=True)
class AheadPlan:
    """Kernels to compile ahead: the ``missing`` ones of ``manifest``, on ``jobs`` cores."""

    manifest: Manifest
    missing: list[str]
    jobs: int

    def notice(self) -> str:
        """The one line that says a first use compiles, and how to do it ahead."""
        about = max(10, round(estimated_seconds(self.missing, self.manifest, self.jobs), -1))
        return (
            f"compiling planarloc's kernels for first use ({len(self.missing)} kernels, about {about:.0f} s "
            f"on {self.jobs} core{'s' if self.jobs > 1 else ''}, once); run `planarloc warmup` at install or "
            "image-build time to do it ahead"
        )

    def run(self, update: Update | None = None) -> CompileReport:
        """Compile the missing kernels; a kernel that fails compiles on first use (logged)."""
        report = compile_kernels(self.missing, self.manifest, self.jobs, update)
        if report.failed:
            logger.info("kernels not compiled ahead (they compile on first use): %s", report.failed)
        return report


def plan_ahead(steps: Sequence[str], jobs: int | None = None) -> AheadPlan | None:
    """What compiling ahead for the warm-up ``steps`` would do; None when nothing is to be done
    (all cached, a cache that cannot keep kernels, an unreadable list: warned, or :func:`compile_lazily`)."""
    if _lazy["depth"]:
        return None
    try:
        manifest = load_manifest()
    except ManifestError as exc:
        logger.warning("%s; kernels compile on first use", exc)
        return None
    missing = missing_kernels(manifest.for_steps(steps), manifest)
    if not missing or not kernels_persist(missing[0]):
        return None
    return AheadPlan(manifest, missing, max(1, int(jobs or os.cpu_count() or 1)))


def compile_ahead(
    steps: Sequence[str],
    jobs: int | None = None,
    update: Update | None = None,
    notify: Callable[[str], None] | None = None,
) -> CompileReport | None:
    """Compile the kernels of ``steps`` that numba's cache misses, on ``jobs`` cores (default: all).

    ``notify`` receives the one-line notice first (default: logged at INFO); ``update`` the
    progress. Returns what was compiled, or None when nothing was to be done (:func:`plan_ahead`)."""
    plan = plan_ahead(steps, jobs)
    if plan is None:
        return None
    (notify or logger.info)(plan.notice())
    return plan.run(update)
