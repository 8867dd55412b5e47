"""A bounded pool of worker processes for CPU-bound requests, driven from an asyncio event loop.

Each worker is its own single-process executor (spawned, so no state leaks from the server's
threads), opens the maps once in its initializer and then serves requests one at a time. Jobs
wait in one FIFO queue; admission is bounded: at most ``workers + queue_size`` requests are
admitted (running or waiting), the next is refused with :class:`Overloaded` at once (the service
answers 503 + ``Retry-After``), so memory stays bounded under any load.

A worker that dies (killed, out of memory, segfault) fails only the request it was running
(:class:`WorkerDied`); its executor is replaced and the pool keeps serving.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from planarloc.serve import worker

logger = logging.getLogger(__name__)


class Overloaded(RuntimeError):
    """The queue is full; retry after ``retry_after_s`` seconds."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"server busy: {retry_after_s} s until retry")
        self.retry_after_s = retry_after_s


class WorkerDied(RuntimeError):
    """The worker process running the request exited; the request was not completed."""


@dataclass
class _Job:
    fn: Callable[..., Any]
    args: tuple
    future: asyncio.Future


class WorkerPool:
    """``workers`` processes with the maps open, one FIFO queue of at most ``queue_size`` waiting jobs.

    Args:
        maps: ``{name: path}`` of the maps every worker opens read-only.
        workers: number of worker processes (>= 1).
        queue_size: admitted jobs waiting for a worker beyond the running ones (>= 0).

    Use inside a running event loop: ``await pool.start()``, ``await pool.run(fn, *args)``,
    ``await pool.close()``.
    """

    def __init__(self, maps: Mapping[str, str | Path], workers: int = 2, queue_size: int = 8) -> None:
        if workers < 1:
            raise ValueError(f"--workers: need at least 1 worker process, got {workers}")
        if queue_size < 0:
            raise ValueError(f"--queue: must be >= 0, got {queue_size}")
        self.maps = {k: str(v) for k, v in maps.items()}
        self.workers = int(workers)
        self.queue_size = int(queue_size)
        self.admitted = 0
        self.busy = 0
        self.restarts = 0
        self.pids: list[int | None] = [None] * self.workers
        self._ctx = multiprocessing.get_context("spawn")
        self._executors: list[ProcessPoolExecutor] = []
        self._queue: asyncio.Queue[_Job] | None = None
        self._tasks: list[asyncio.Task] = []

    @property
    def capacity(self) -> int:
        return self.workers + self.queue_size

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            1, mp_context=self._ctx, initializer=worker.open_localizers, initargs=(self.maps,)
        )

    async def start(self) -> None:
        """Spawn the workers and wait until each has opened its maps (raises if a map fails to open)."""
        self._queue = asyncio.Queue()
        self._executors = [self._new_executor() for _ in range(self.workers)]
        loop = asyncio.get_running_loop()
        try:
            pids = await asyncio.gather(*(loop.run_in_executor(ex, worker.ping) for ex in self._executors))
        except BrokenProcessPool:
            await self.close()
            raise ValueError(
                "a worker process failed to open the maps (run `planarloc map info` on each)"
            ) from None
        self.pids = list(pids)
        self._tasks = [asyncio.create_task(self._serve(i)) for i in range(self.workers)]

    def admit(self) -> None:
        """Reserve a place for one request, or raise :class:`Overloaded`; pair with :meth:`release`."""
        if self.admitted >= self.capacity:
            raise Overloaded(retry_after_s=1 + (self.queue_size + self.workers - 1) // self.workers)
        self.admitted += 1

    def release(self) -> None:
        self.admitted -= 1

    async def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn(*args)`` in a worker (call :meth:`admit` first). Raises what ``fn`` raised,
        or :class:`WorkerDied`."""
        if self._queue is None:
            raise RuntimeError("WorkerPool.start() was not awaited")
        job = _Job(fn, args, asyncio.get_running_loop().create_future())
        self._queue.put_nowait(job)
        return await job.future

    async def _serve(self, slot: int) -> None:
        loop = asyncio.get_running_loop()
        assert self._queue is not None
        while True:
            job = await self._queue.get()
            if job.future.cancelled():  # the client went away while the job waited
                continue
            self.busy += 1
            try:
                result = await loop.run_in_executor(self._executors[slot], job.fn, *job.args)
            except BrokenProcessPool:
                logger.warning("worker %d (pid %s) died; restarting it", slot, self.pids[slot])
                self._executors[slot].shutdown(wait=False, cancel_futures=True)
                self._executors[slot] = self._new_executor()
                self.restarts += 1
                if not job.future.done():
                    job.future.set_exception(
                        WorkerDied("the worker process running this request died; retry")
                    )
                try:
                    self.pids[slot] = await loop.run_in_executor(self._executors[slot], worker.ping)
                except BrokenProcessPool:
                    logger.error("worker %d cannot restart", slot)
                    self.pids[slot] = None
            except BaseException as exc:  # noqa: BLE001 - forwarded to the request
                if isinstance(exc, asyncio.CancelledError):
                    raise
                if not job.future.done():
                    job.future.set_exception(exc)
            else:
                if not job.future.done():
                    job.future.set_result(result)
            finally:
                self.busy -= 1

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for ex in self._executors:
            ex.shutdown(wait=False, cancel_futures=True)
        self._tasks, self._executors = [], []
