"""Compiling kernels into numba's on-disk cache on several cores.

``jobs`` worker processes (``python -m planarloc.compile --compile-worker``) each compile one
kernel at a time, handed out once every kernel it calls (read from its bytecode) is compiled,
longest remaining chain of compile time first; a worker loads those callees from the cache
instead of compiling them again.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TextIO

from planarloc.compile.dispatchers import dispatcher, kernel_dependencies
from planarloc.compile.manifest import Manifest
from planarloc.compile.signatures import numba_types, parse_signature
from planarloc.compile.steps import Update

COMPILE_STAGE = "compile kernels"
WORKER_COMMAND = ("-m", "planarloc.compile", "--compile-worker")


class _Schedule:
    """Hands out kernels whose callees are compiled, longest remaining chain of compile time first."""

    def __init__(self, deps: dict[str, set[str]], cost: dict[str, float]) -> None:
        self.deps, self.pending = deps, set(deps)
        self.running: set[str] = set()
        self.done: set[str] = set()
        users: dict[str, set[str]] = {k: set() for k in deps}
        for k, ds in deps.items():
            for d in ds:
                users[d].add(k)
        self.chain: dict[str, float] = {}

        def chain(k: str, seen: frozenset) -> float:
            if k not in self.chain:
                self.chain[k] = cost.get(k, 1.0) + max(
                    (chain(u, seen | {k}) for u in users[k] if u not in seen), default=0.0
                )
            return self.chain[k]

        for k in deps:
            chain(k, frozenset())
        self._cv = threading.Condition()

    def take(self) -> str | None:
        with self._cv:
            while self.pending:
                ready = [k for k in self.pending if self.deps[k] <= self.done]
                if not ready and not self.running:
                    ready = list(self.pending)  # a call cycle: compile one anyway
                if ready:
                    k = max(ready, key=lambda r: (self.chain[r], r))
                    self.pending.discard(k)
                    self.running.add(k)
                    return k
                self._cv.wait()
            return None

    def finish(self, key: str) -> None:
        with self._cv:
            self.running.discard(key)
            self.done.add(key)
            self._cv.notify_all()


@dataclass
class CompileReport:
    """What :func:`compile_kernels` did: counts, failures, the wall ``seconds``, and the wall
    seconds of each kernel's task (``task_seconds``) and each worker's busy time (``busy_seconds``)."""

    compiled: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    task_seconds: dict[str, float] = field(default_factory=dict)
    busy_seconds: list[float] = field(default_factory=list)


def estimated_seconds(keys: Sequence[str], manifest: Manifest, jobs: int) -> float:
    """About how long compiling ``keys`` on ``jobs`` cores takes: the larger of the CPU seconds
    per core and the longest chain of kernels that wait for each other."""
    keys = [k for k in keys if k in manifest.kernels]
    if not keys:
        return 0.0
    cost = {k: manifest.kernels[k].compile_s for k in keys}
    schedule = _Schedule(kernel_dependencies(keys), cost)
    return max(sum(cost.values()) / max(jobs, 1), max(schedule.chain.values()))


def _drive(
    proc: subprocess.Popen[str],
    schedule: _Schedule,
    manifest: Manifest,
    report: CompileReport,
    lock: threading.Lock,
    update: Update | None,
) -> None:
    """Feed one worker process kernels from ``schedule`` until none is left or the worker ends."""
    stdin, stdout = proc.stdin, proc.stdout
    if stdin is None or stdout is None:
        raise ValueError("a compile worker must be started with stdin=PIPE and stdout=PIPE")
    total = len(schedule.deps)
    with lock:
        worker = len(report.busy_seconds)
        report.busy_seconds.append(0.0)
    while (key := schedule.take()) is not None:
        t0 = time.perf_counter()
        try:
            stdin.write(json.dumps({"key": key, "signatures": manifest.kernels[key].signatures}) + "\n")
            stdin.flush()
            reply = stdout.readline()
        except (OSError, ValueError):
            reply = ""
        errors = json.loads(reply)["errors"] if reply else ["the worker process ended"]
        schedule.finish(key)
        took = time.perf_counter() - t0
        with lock:
            report.task_seconds[key] = took
            report.busy_seconds[worker] += took
            if errors:
                report.failed[key] = "; ".join(errors)
            else:
                report.compiled += 1
            done = len(schedule.done)
        if update is not None:
            update(COMPILE_STAGE, done, total)
        if not reply:
            return


def _stop(workers: list[subprocess.Popen[str]]) -> None:
    """Close the workers' input (they end) and wait for them; kill one that does not end."""
    for p in workers:
        if p.poll() is None and p.stdin is not None:
            try:
                p.stdin.close()
            except OSError:
                pass
    for p in workers:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


def compile_kernels(
    keys: Sequence[str], manifest: Manifest, jobs: int | None = None, update: Update | None = None
) -> CompileReport:
    """Compile kernels into numba's on-disk cache in ``jobs`` worker processes (default: one per
    core; module docstring). Returns what was compiled and what failed (those compile on first use)."""
    t0 = time.perf_counter()
    keys = sorted(set(keys) & set(manifest.kernels))
    report = CompileReport()
    if not keys:
        return report
    schedule = _Schedule(kernel_dependencies(keys), {k: manifest.kernels[k].compile_s for k in keys})
    jobs = max(1, min(int(jobs or os.cpu_count() or 1), len(keys)))
    lock = threading.Lock()
    if update is not None:
        update(COMPILE_STAGE, 0, len(keys))
    workers = [
        subprocess.Popen(
            [sys.executable, *WORKER_COMMAND],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        for _ in range(jobs)
    ]
    threads = [
        threading.Thread(target=_drive, args=(p, schedule, manifest, report, lock, update), daemon=True)
        for p in workers
    ]
    try:
        for t in threads:
            t.start()
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    finally:
        _stop(workers)
    report.seconds = time.perf_counter() - t0
    return report


def serve_compile_requests(requests: Iterable[str], out: TextIO) -> None:
    """A worker process's loop: compile the kernels named in ``requests`` (one JSON line each:
    ``{"key", "signatures"}``) and answer each on ``out`` with ``{"key", "seconds", "errors"}``."""
    names = numba_types()
    for line in requests:
        task = json.loads(line)
        t0, errors = time.process_time(), []
        d = dispatcher(task["key"])
        for text in task["signatures"]:
            sig = parse_signature(text, names)
            if d is None or sig is None:
                errors.append(f"{task['key']}{text}: no such kernel or signature")
                continue
            try:
                d.compile(sig)
            except Exception as exc:  # noqa: BLE001 - reported; the kernel compiles on first use
                errors.append(f"{task['key']}{text}: {type(exc).__name__}: {exc}".splitlines()[0])
        out.write(
            json.dumps({"key": task["key"], "seconds": time.process_time() - t0, "errors": errors}) + "\n"
        )
        out.flush()
