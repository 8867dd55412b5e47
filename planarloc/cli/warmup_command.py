"""`planarloc warmup`: compile every numba kernel a query uses into numba's on-disk cache, on all cores.

The compiling is :mod:`planarloc.compile`'s; this module is its command-line front: the
``warmup`` command, :func:`compile_ahead` for the commands that estimate poses (the one-line
notice and the progress bar on stderr), and :func:`first_use` for ``planarloc localize``: on an
empty cache its queries run with kernels as Python while a detached process compiles them, so a
first pose comes in seconds instead of after the whole compile. ``planarloc warmup`` at install or
image-build time (``RUN planarloc warmup`` after ``pip install``, as root, before ``USER``) writes
the cache once, and queries only load it, also as a user who cannot write the install (the
repository's ``Dockerfile`` does this). A kernel list that cannot be read, or is not of its shape, fails
``warmup`` with one line naming the file; the other commands warn in one line and let the
kernels compile on first use.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note, progress_bar
from planarloc.cli.exit_codes import WARMUP_RESUMES
from planarloc.cli.progress import Update
from planarloc.compile import compile_kernels, load_manifest, plan_ahead, run_steps
from planarloc.compile.cache import kernels_persist, missing_kernels
from planarloc.compile.first_use import FirstUse, first_use_or_compile

NOWHERE = (
    "nowhere to keep compiled kernels: planarloc's install is read-only here and neither HOME nor the temp "
    "folder is writable; run `planarloc warmup` where the install is writable (e.g. when the image is "
    "built, before USER), or set NUMBA_CACHE_DIR to a writable folder"
)


def compile_ahead(steps: Sequence[str], jobs: int | None = None, progress: Update | None = None) -> None:
    """Before a command estimates poses: if kernels of the warm-up ``steps`` are not in numba's
    cache, say so in one line on stderr and compile them on every core, with a progress bar
    (:func:`planarloc.compile.plan_ahead`): ``progress``, the caller's when it shows one already
    (a terminal holds one live display at a time), else a new one."""
    plan = plan_ahead(steps, jobs)
    if plan is None:
        return
    note(plan.notice())
    if progress is not None:
        plan.run(progress)
        return
    with progress_bar() as update:
        plan.run(update)


@contextmanager
def first_use(steps: Sequence[str], wait: bool = False) -> Iterator[Callable[[], None]]:
    """Around a command's queries: if kernels of the warm-up ``steps`` are not in numba's cache,
    compile them in a detached process and run the queries meanwhile with the kernels as Python
    (:mod:`planarloc.compile.first_use`), saying so in one line. Yields ``poll``: call it between
    queries; once the compile has ended the next queries run compiled. ``wait``: compile on every
    core first instead (:func:`compile_ahead`), the faster choice for many queries."""
    started = first_use_or_compile(steps, note, wait, compile_first=compile_ahead)
    if started is None:
        yield lambda: None
        return
    first: FirstUse = started

    def poll() -> None:
        if first.poll():
            note("planarloc's kernels are compiled: the next queries run compiled")

    try:
        yield poll
    finally:
        first.end()


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "warmup",
        "compile every numba kernel once, on all cores (run at install or image build time)",
        """Compile every numba kernel a query uses into numba's on-disk cache: in parallel worker
                    processes (--jobs, default one per core), then by running each estimator once on small
                    generated scenes, which loads them all. The first run on a machine takes about 3 minutes
                    of CPU, spread over the cores; later runs, and queries, only load the cache. Progress goes
                    to stderr (plain lines without a terminal). In a Dockerfile, after pip install:
                    RUN planarloc warmup""",
        ["planarloc warmup", "planarloc warmup --jobs 8"],
        run,
        interrupted=WARMUP_RESUMES,
    )
    p.add_argument("--jobs", "-j", type=int, default=None, help="worker processes (default: one per core)")


def run(args: argparse.Namespace) -> int:
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs: expected an integer >= 1, got {args.jobs}")
    t0 = time.perf_counter()
    manifest = load_manifest()
    missing = missing_kernels(manifest.kernels, manifest)
    if missing and not kernels_persist(missing[0]):
        raise ValueError(NOWHERE)
    with progress_bar() as update:
        report = compile_kernels(missing, manifest, args.jobs, update)
        times = run_steps(update=update)
    compiled = (
        f"{report.compiled} kernels compiled on {max(1, args.jobs or os.cpu_count() or 1)} cores"
        if missing
        else "every listed kernel was cached"
    )
    failed = f", {len(report.failed)} compiled by the steps instead" if report.failed else ""
    slowest = max(times, key=times.__getitem__)
    info(
        f"warm-up done in {time.perf_counter() - t0:.1f} s ({compiled}{failed}; "
        f"slowest step: {slowest}, {times[slowest]:.1f} s)"
    )
    return 0
