"""A bounded pool of worker processes for CPU-bound requests, driven from an asyncio event loop.

Each worker is a spawned process (no state leaks from the server's threads) that opens the maps
once (:func:`planarloc.serve.worker.worker_main`) and then runs jobs one at a time, sent over a
pipe. Scheduling:

- **Admission is bounded**: at most ``workers + queue_size`` requests are admitted (running or
  waiting); the next is refused with :class:`Overloaded` at once (the service answers 503 +
  ``Retry-After``), so memory stays bounded under any load. A request is admitted only once its
  body has arrived (:mod:`planarloc.serve.form`), so slow clients hold no place.
- **Waiting is bounded**: a job that has not started after ``queue_timeout_s`` is withdrawn
  (:class:`QueueTimeout`, 503), and a job that runs longer than ``job_timeout_s`` has its worker
  killed and replaced (:class:`WorkerDied`, 503).
- **Affinity**: a job may be pinned to one worker (``slot``): the frames of a session run in the
  worker that holds the session's state, in arrival order; unpinned jobs go to whichever
  worker is free first (a worker takes its pinned jobs first).

Every worker's process sentinel is watched by the event loop, so a worker that dies (killed,
out of memory, segfault) is seen **at once**, idle or busy: it fails only the request it was
running and the jobs pinned to it (:class:`WorkerDied`), its sessions are reported lost
(``on_worker_lost``), and it is replaced (with a growing delay if it keeps dying at start).
:meth:`WorkerPool.alive` is the truth about the processes at the moment it is asked.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planarloc.compile.background import BackgroundCompile
from planarloc.serve import worker
from planarloc.serve.map_watch import MapFingerprint
from planarloc.serve.requests import RequestError, ServerFault
from planarloc.serve.settings import DEFAULT_JOB_TIMEOUT_S, DEFAULT_QUEUE_TIMEOUT_S

logger = logging.getLogger(__name__)

#: Time for a (re)started worker to open its maps (and, on an empty kernel cache with
#: ``PLANARLOC_COMPILE=wait``, for the compile it waits for: :func:`worker.start_kernels`).
STARTUP_TIMEOUT_S = 600.0


class Overloaded(RuntimeError):
    """The queue is full; retry after ``retry_after_s`` seconds."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"server busy: {retry_after_s} s until retry")
        self.retry_after_s = retry_after_s


class QueueTimeout(RuntimeError):
    """The job waited ``queue_timeout_s`` without a worker taking it; it was withdrawn."""


class WorkerDied(RuntimeError):
    """The worker process running the request exited (or was killed for running too long)."""


class _Died(Exception):
    pass


class _TimedOut(Exception):
    pass


@dataclass
class _Job:
    fn: Callable[..., Any]
    args: tuple
    future: asyncio.Future
    slot: int | None = None
    started: bool = False


@dataclass
class _Worker:
    process: Any  # multiprocessing.Process
    conn: Any  # multiprocessing.connection.Connection
    pid: int | None = None
    ready: bool = False
    dead: bool = False
    compiling: BackgroundCompile | None = None  # while it runs, the worker's kernels run as Python
    started_at: float = field(default_factory=time.monotonic)


def _log_control_failure(future: asyncio.Future) -> None:
    """Done callback of a control job (:meth:`WorkerPool.post`): its failure is only logged."""
    if not future.cancelled() and future.exception() is not None:
        logger.warning("control job failed: %s", future.exception())


class WorkerPool:
    """``workers`` processes with the maps open, FIFO queues of at most ``queue_size`` waiting jobs.

    Args:
        maps: ``{name: path}`` of the maps every worker opens read-only.
        workers: number of worker processes (>= 1).
        queue_size: admitted jobs waiting for a worker beyond the running ones (>= 0).
        queue_timeout_s: longest wait of a job for a worker.
        job_timeout_s: longest run of a job; beyond it the worker is killed and replaced.
        expected: the server's fingerprints of the maps (:mod:`planarloc.serve.map_watch`); a
            worker that opened another version reports it through ``on_map_changed``.

    Use inside a running event loop: ``await pool.start()``, ``await pool.run(fn, *args)``,
    ``await pool.close()``. Callbacks (set before ``start``): ``on_worker_lost(slot, reason)``,
    ``on_map_changed(name, change)``.
    """

    def __init__(
        self,
        maps: Mapping[str, str | Path],
        workers: int = 2,
        queue_size: int = 8,
        *,
        queue_timeout_s: float = DEFAULT_QUEUE_TIMEOUT_S,
        job_timeout_s: float = DEFAULT_JOB_TIMEOUT_S,
        expected: Mapping[str, MapFingerprint] | None = None,
    ) -> None:
        if workers < 1:
            raise ValueError(f"--workers: need at least 1 worker process, got {workers}")
        if queue_size < 0:
            raise ValueError(f"--queue: must be >= 0, got {queue_size}")
        if not queue_timeout_s > 0 or not job_timeout_s > 0:
            raise ValueError(
                f"--queue-timeout and --job-timeout must be > 0 s, got {queue_timeout_s} and {job_timeout_s}"
            )
        self.maps = {k: str(v) for k, v in maps.items()}
        self.expected = dict(expected or {})
        self.workers = int(workers)
        self.queue_size = int(queue_size)
        self.queue_timeout_s = float(queue_timeout_s)
        self.job_timeout_s = float(job_timeout_s)
        self.admitted = 0
        self.busy = 0
        self.restarts = 0
        self.deaths = 0
        self.on_worker_lost: Callable[[int, str], None] | None = None
        self.on_map_changed: Callable[[str, str], None] | None = None
        self._ctx = multiprocessing.get_context("spawn")
        self._current: list[_Worker | None] = [None] * self.workers
        self._pinned: list[deque[_Job]] = [deque() for _ in range(self.workers)]
        self._shared: deque[_Job] = deque()
        self._wake: list[asyncio.Event] = []
        self._tasks: list[asyncio.Task] = []
        self._restarting: set[int] = set()
        self._threads: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closing = False

    @property
    def capacity(self) -> int:
        return self.workers + self.queue_size

    # ---- processes --------------------------------------------------------------------------
    def _spawn(self) -> _Worker:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(
            target=worker.worker_main,
            args=(child, self.maps, self.expected),
            daemon=True,
            name="planarloc-worker",
        )
        proc.start()
        child.close()
        return _Worker(proc, parent)

    @staticmethod
    def _wait_ready(w: _Worker, timeout: float) -> tuple:
        ready = multiprocessing.connection.wait([w.conn, w.process.sentinel], timeout)
        if w.conn in ready:
            try:
                return w.conn.recv()
            except (EOFError, OSError):
                pass
        if not ready:
            return ("failed", f"did not open the maps within {timeout:.0f} s")
        return ("failed", f"exited with code {w.process.exitcode} while opening the maps")

    async def _boot(self, slot: int) -> None:
        """Start the worker of ``slot`` and wait until it has opened the maps (raises ValueError if not)."""
        assert self._loop is not None
        w = self._spawn()
        self._current[slot] = w
        self._loop.add_reader(w.process.sentinel, self._on_death, slot, w)
        answer = await self._loop.run_in_executor(self._threads, self._wait_ready, w, STARTUP_TIMEOUT_S)
        if answer[0] != "ready":
            self._kill(w)
            raise ValueError(
                f"a worker process failed to open the maps ({answer[1]}); run `planarloc map info` "
                "on each map"
            )
        _, w.pid, changed, w.compiling = answer
        for name, change in changed.items():
            logger.error(
                "worker %d (pid %d) opened another version of map %s than the server's (%s)",
                slot,
                w.pid,
                name,
                change,
            )
            if self.on_map_changed is not None:
                self.on_map_changed(name, change)
        if w.dead:  # died between its answer and now
            raise ValueError("a worker process exited right after opening the maps")
        w.ready = True
        self._wake[slot].set()

    def _kill(self, w: _Worker) -> None:
        try:
            if w.process.is_alive():
                os.kill(w.process.pid, signal.SIGKILL)
        except (ProcessLookupError, OSError, ValueError):
            pass

    def _on_death(self, slot: int, w: _Worker) -> None:
        """The sentinel of a worker became readable: the process exited. Runs in the event loop."""
        assert self._loop is not None
        self._loop.remove_reader(w.process.sentinel)
        if w.dead:
            return
        w.dead = True
        w.ready = False
        w.process.join(0)  # reap it: no zombie, and is_alive() is False from now on
        if self._closing or self._current[slot] is not w:
            return
        self.deaths += 1
        logger.warning(
            "worker %d (pid %s) died (exit code %s); restarting it", slot, w.pid, w.process.exitcode
        )
        for job in self._pinned[slot]:
            if not job.future.done():
                job.future.set_exception(WorkerDied("the worker process holding this session died; retry"))
        self._pinned[slot].clear()
        if self.on_worker_lost is not None:
            self.on_worker_lost(slot, "was lost: the worker process serving it died")
        if slot not in self._restarting:
            self._restarting.add(slot)
            self._tasks.append(asyncio.ensure_future(self._restart(slot)))

    async def _restart(self, slot: int) -> None:
        delay = 0.0
        try:
            while not self._closing:
                if delay:
                    await asyncio.sleep(delay)
                try:
                    await self._boot(slot)
                    self.restarts += 1
                    logger.info("worker %d restarted (pid %s)", slot, self.pids[slot])
                    return
                except ValueError as exc:
                    delay = min(30.0, max(1.0, 2 * delay))
                    logger.error("worker %d cannot restart (%s); trying again in %.0f s", slot, exc, delay)
        finally:
            self._restarting.discard(slot)

    def alive(self) -> list[bool]:
        """Per worker: its process runs and has its maps open (checked on the process, now)."""
        out = []
        for w in self._current:
            out.append(w is not None and w.ready and not w.dead and w.process.is_alive())
        return out

    def as_python(self) -> int:
        """Live workers whose kernels run as Python: they started on an empty kernel cache and the
        compile they share still runs (checked now). Once it has ended, each worker switches to
        compiled kernels before its next request, so none counts any more."""
        count = 0
        for ok, w in zip(self.alive(), self._current):
            if w is None or w.compiling is None:
                continue
            if w.compiling.done():
                w.compiling = None
            elif ok:
                count += 1
        return count

    @property
    def pids(self) -> list[int | None]:
        return [w.pid if ok and w is not None else None for ok, w in zip(self.alive(), self._current)]

    # ---- lifecycle --------------------------------------------------------------------------
    async def start(self) -> None:
        """Spawn the workers and wait until each has opened its maps (ValueError if one cannot)."""
        self._loop = asyncio.get_running_loop()
        self._threads = ThreadPoolExecutor(
            max_workers=2 * self.workers + 2, thread_name_prefix="planarloc-pool"
        )
        self._wake = [asyncio.Event() for _ in range(self.workers)]
        try:
            await asyncio.gather(*(self._boot(i) for i in range(self.workers)))
        except ValueError:
            await self.close()
            raise
        self._tasks = [asyncio.ensure_future(self._serve(i)) for i in range(self.workers)]

    async def close(self) -> None:
        self._closing = True
        for t in self._tasks:
            t.cancel()
        for w in self._current:
            if w is None:
                continue
            if self._loop is not None:
                self._loop.remove_reader(w.process.sentinel)
            try:
                w.conn.close()
            except OSError:
                pass
            w.process.terminate()
        deadline = time.monotonic() + 5
        for w in self._current:
            if w is not None:
                w.process.join(max(0.0, deadline - time.monotonic()))
                self._kill(w)
                w.process.join(1)
        for queue in (*self._pinned, self._shared):
            for job in queue:
                if not job.future.done():
                    job.future.set_exception(WorkerDied("the server is shutting down"))
            queue.clear()
        self._tasks, self._current = [], [None] * self.workers
        if self._threads is not None:
            self._threads.shutdown(wait=False, cancel_futures=True)

    # ---- admission and jobs -----------------------------------------------------------------
    def admit(self) -> None:
        """Reserve a place for one request, or raise :class:`Overloaded`; pair with :meth:`release`."""
        if self.admitted >= self.capacity:
            raise Overloaded(retry_after_s=1 + (self.queue_size + self.workers - 1) // self.workers)
        self.admitted += 1

    def release(self) -> None:
        self.admitted -= 1

    def _enqueue(self, job: _Job, front: bool = False) -> None:
        if job.slot is None:
            self._shared.append(job)
            for event in self._wake:
                event.set()
        else:
            queue = self._pinned[job.slot]
            queue.appendleft(job) if front else queue.append(job)
            self._wake[job.slot].set()

    async def run(self, fn: Callable[..., Any], *args: Any, slot: int | None = None) -> Any:
        """Run ``fn(*args)`` in a worker (``slot``: that one), after :meth:`admit`.

        Raises:
            what ``fn`` raised in the worker (:class:`RequestError`, :class:`ServerFault`),
            :class:`QueueTimeout` or :class:`WorkerDied`.
        """
        if self._loop is None:
            raise RuntimeError("WorkerPool.start() was not awaited")
        job = _Job(fn, args, self._loop.create_future(), slot)
        self._enqueue(job)
        try:
            done, _ = await asyncio.wait({job.future}, timeout=self.queue_timeout_s)
            if not done and not job.started:
                job.future.cancel()
                raise QueueTimeout(f"no worker was free within {self.queue_timeout_s:g} s; retry later")
            return await job.future
        except asyncio.CancelledError:  # the client went away: a job that has not started is withdrawn
            if not job.started:
                job.future.cancel()
            raise

    def post(self, slot: int, fn: Callable[..., Any], *args: Any) -> None:
        """Run a small control job (e.g. free sessions) on one worker before its other jobs; not
        admitted, its answer only logged."""
        if self._loop is None or self._current[slot] is None or self._current[slot].dead:  # type: ignore[union-attr]
            return
        job = _Job(fn, args, self._loop.create_future(), slot)
        job.future.add_done_callback(_log_control_failure)
        self._enqueue(job, front=True)

    def _take(self, slot: int) -> _Job | None:
        for queue in (self._pinned[slot], self._shared):
            while queue:
                job = queue.popleft()
                if not job.future.done():
                    return job
        return None

    def _call(self, w: _Worker, fn: Callable[..., Any], args: tuple) -> tuple:
        """Send one job to a worker and wait for its answer (in a thread)."""
        try:
            w.conn.send((fn, args))
        except (EOFError, OSError, ValueError):
            raise _Died from None
        ready = multiprocessing.connection.wait([w.conn, w.process.sentinel], self.job_timeout_s)
        if w.conn in ready:
            try:
                return w.conn.recv()
            except (EOFError, OSError):
                raise _Died from None
        if not ready:
            raise _TimedOut
        raise _Died

    async def _serve(self, slot: int) -> None:
        assert self._loop is not None
        while True:
            w = self._current[slot]
            job = self._take(slot) if w is not None and w.ready and not w.dead else None
            if w is None or job is None:
                self._wake[slot].clear()
                await self._wake[slot].wait()
                continue
            job.started = True
            self.busy += 1
            error: BaseException | None
            try:
                answer = await self._loop.run_in_executor(self._threads, self._call, w, job.fn, job.args)
            except _Died:
                error = WorkerDied("the worker process running this request died; retry")
            except _TimedOut:
                logger.error(
                    "worker %d (pid %s): a request ran longer than %g s; killing the worker",
                    slot,
                    w.pid,
                    self.job_timeout_s,
                )
                self._kill(w)  # its sentinel fires: the worker is replaced
                error = WorkerDied(
                    f"the request ran longer than {self.job_timeout_s:g} s; its worker was restarted"
                )
            else:
                error = None
            finally:
                self.busy -= 1
            if job.future.done():
                continue
            if error is not None:
                job.future.set_exception(error)
            elif answer[0] == "ok":
                job.future.set_result(answer[1])
            elif answer[0] == "request":
                job.future.set_exception(RequestError(answer[1], answer[2], answer[3]))
            else:
                job.future.set_exception(ServerFault(answer[1]))
