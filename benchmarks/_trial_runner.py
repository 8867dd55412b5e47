"""Run independent benchmark trials in worker processes with a progress line on stderr; the command
line the synthetic benchmarks (``accuracy.py``, ``robustness.py``) share."""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class TrialPlan:
    """What the shared flags ask for."""

    args: argparse.Namespace
    trials: int  # scenes per cell
    methods: tuple[str, ...]  # ours
    names: tuple[str, ...]  # ours, then the PoseLib peer unless --no-poselib


def parse_trial_args(ap: argparse.ArgumentParser, argv: list[str] | None, peer: str) -> TrialPlan | None:
    """Add the last shared flag (``--no-poselib``) and parse; ``--quick`` means 20 trials per cell.
    None, with the error on stderr, when --trials or --jobs is below 1."""
    ap.add_argument("--no-poselib", action="store_true", help="skip the PoseLib peer")
    args = ap.parse_args(argv)
    trials = 20 if args.quick else args.trials
    if trials < 1 or args.jobs < 1:
        print("error: --trials and --jobs must be >= 1", file=sys.stderr)
        return None
    methods = tuple(args.methods)
    return TrialPlan(args, trials, methods, methods + (() if args.no_poselib else (peer,)))


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
