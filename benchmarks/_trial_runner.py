"""Run independent benchmark trials in worker processes with a progress line on stderr."""

from __future__ import annotations

import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence


def run_trials(
    label: str, tasks: Sequence, run_trial: Callable[[object], dict], jobs: int, warm_up: Callable[[], None]
) -> list[dict]:
    """Warm up (numba compile) in this process, then run ``run_trial`` on every task.

    With ``jobs > 1`` the tasks run in forked workers, which inherit the compiled kernels;
    results come back in completion order.
    """
    total, results = len(tasks), []
    t_start, last = time.perf_counter(), 0.0

    def progress(done: int) -> None:
        nonlocal last
        now = time.perf_counter() - t_start
        if done == total or now - last > 10.0:
            last = now
            eta = now / done * (total - done) if done else float("nan")
            print(
                f"[{label}] {done}/{total} scenes ({100 * done / total:.0f}%), {now:.0f} s elapsed, "
                f"~{eta:.0f} s left",
                file=sys.stderr,
                flush=True,
            )

    print(f"[{label}] warming up (numba compile or cache load) ...", file=sys.stderr, flush=True)
    warm_up()
    print(
        f"[{label}] warm-up {time.perf_counter() - t_start:.0f} s; {total} scenes on {jobs} worker(s)",
        file=sys.stderr,
        flush=True,
    )
    t_start = time.perf_counter()
    if jobs <= 1:
        for i, task in enumerate(tasks):
            results.append(run_trial(task))
            progress(i + 1)
    else:
        with mp.get_context("fork").Pool(jobs) as pool:
            for i, res in enumerate(pool.imap_unordered(run_trial, tasks, chunksize=1)):
                results.append(res)
                progress(i + 1)
    return results
