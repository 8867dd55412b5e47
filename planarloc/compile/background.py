"""Compiling the kernels a command needs in a detached process of its own, while the command
answers its first queries with kernels run as Python (:mod:`.interpreted`).

:func:`compile_in_background` starts ``python -m planarloc.compile --background STEP...``: a
process in a session of its own (Ctrl-C on the command does not stop it, and it outlives a
command that has finished its queries) that compiles the kernels numba's cache misses for the
warm-up steps (:func:`.ahead.plan_ahead`), writes its progress to a log file and exits. The next
commands load what it wrote.

One such compile runs per kernel cache: its lock file ``<temp>/planarloc-<uid>/compile/<key>.lock``
(``key`` names numba's cache folder setting and planarloc's install) is held with
``fcntl.flock`` by the compiling process for its whole life (it inherits the descriptor the
starter locked, so no other command can slip in between) and released by the system when it ends,
also when it is killed. A command that finds the lock held does not start a second compile and
asks :meth:`BackgroundCompile.done` whether it is still held.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from planarloc.numerics.user_folders import user_temp_folder

__all__ = ["BackgroundCompile", "compile_in_background", "compile_running", "lock_path"]

BACKGROUND_COMMAND = ("-m", "planarloc.compile")


def lock_path() -> Path:
    """The lock file of this kernel cache's background compile (its folder created, mode 0700)."""
    package = Path(__file__).resolve().parents[1]
    where = f"{os.environ.get('NUMBA_CACHE_DIR', '')}\0{package}"
    key = hashlib.sha256(where.encode()).hexdigest()[:16]
    return user_temp_folder("compile") / f"{key}.lock"


def compile_running() -> bool:
    """Whether a background compile of this kernel cache (``NUMBA_CACHE_DIR``) runs now."""
    return _held(lock_path())


def _held(lock: Path) -> bool:
    """Whether a process holds the lock (a compile is running)."""
    try:
        fd = os.open(lock, os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # closing also releases a lock taken just now
    return False


@dataclass
class BackgroundCompile:
    """A compile running in the background: ``pid`` of the process (read from the lock file when
    another command started it), its ``log``, and whether this command started it (``ours``)."""

    lock: Path
    log: Path
    pid: int | None
    ours: bool
    _process: subprocess.Popen | None = None

    def done(self) -> bool:
        """Whether the compile has ended (its kernels are in the cache, or it failed: the log says why)."""
        if self._process is not None:
            return self._process.poll() is not None
        return not _held(self.lock)

    def seen_from_elsewhere(self) -> BackgroundCompile:
        """This compile as another process sees it (picklable, without the process handle):
        :meth:`done` then asks the lock, which the system releases when the compile ends."""
        return BackgroundCompile(self.lock, self.log, self.pid, ours=False)


def compile_in_background(steps: Sequence[str], jobs: int) -> BackgroundCompile:
    """Start compiling the kernels of the warm-up ``steps`` that the cache misses, on ``jobs``
    worker processes, detached; or, when a compile of this cache is running already, return that
    one (``ours`` False).

    Raises:
        OSError: the lock or log file cannot be written, or the process cannot be started.
    """
    lock = lock_path()
    log = lock.with_suffix(".log")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            text = os.pread(fd, 32, 0).decode(errors="replace").strip()
            return BackgroundCompile(lock, log, int(text) if text.isdigit() else None, ours=False)
        with open(log, "w", encoding="utf-8") as out:
            process = subprocess.Popen(
                [sys.executable, *BACKGROUND_COMMAND, "--jobs", str(jobs), "--background", *steps],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                pass_fds=(fd,),  # the compile holds the lock from here until it ends
                start_new_session=True,
            )
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{process.pid}\n".encode(), 0)
        return BackgroundCompile(lock, log, process.pid, ours=True, _process=process)
    finally:
        os.close(fd)


def run_background_compile(steps: Sequence[str], jobs: int) -> int:
    """The detached process: compile what the cache misses of ``steps`` (progress lines on
    stdout, the log). Returns the exit code."""
    import time

    from planarloc.compile.ahead import plan_ahead

    t0 = time.perf_counter()
    plan = plan_ahead(steps, jobs)
    if plan is None:
        print("nothing to compile: every kernel of these steps is cached", flush=True)
        return 0
    print(plan.notice(), flush=True)

    def update(stage: str, done: int, total: int) -> None:
        print(f"{stage}: {done}/{total} ({time.perf_counter() - t0:.0f} s)", flush=True)

    report = plan.run(update)
    print(
        f"compiled {report.compiled} kernels in {time.perf_counter() - t0:.1f} s"
        + (f"; not compiled (they compile on first use): {report.failed}" if report.failed else ""),
        flush=True,
    )
    return 0
