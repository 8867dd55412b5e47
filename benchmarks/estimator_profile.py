"""Where an estimator's time goes (issue 31): compiled kernels against the Python around them.

Runs the hard protocol of ``robustness.py`` (3 map images, 1.5 px noise, 50 and 20 matches per
pair, 0-60 % outliers, 100 fixed iterations) for one method and reports, per scene, the CPU time
of the whole call, the share spent inside planarloc's compiled kernels (every numba dispatcher of
the package, counted at the outermost call, dispatch and argument unboxing included) and the rest:
the Python and numpy calls between kernels. The same scenes then run through PoseLib's
``estimate_generalized_relative_pose`` (the peer of ``robustness.py``), so the split reads as a
ratio to the peer's time. Each stage of the estimate (the set-up, the searches, the judgement of a
pose, and for a planar pose the short 6DoF search that checks it and the second search of a weak
one) is split the same way.

The kernels are wrapped by a Python timer for this (about 0.3 µs per call): the total is a few
per cent above an uninstrumented run, which is timed first and printed too.

    python benchmarks/estimator_profile.py --method auto --trials 60 --seed 60
    python benchmarks/estimator_profile.py --method 2p1p --no-cross-check --json split.json
    python benchmarks/estimator_profile.py --method auto --dispatch   # numba's dispatch per call too
"""

from __future__ import annotations

import argparse
import copy
import functools
import inspect
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import ModuleType

from numba.core.registry import CPUDispatcher

sys.path.insert(0, str(Path(__file__).resolve().parent))
import robustness as rb  # noqa: E402
from poselib_peer import estimate_query_pose_poselib  # noqa: E402

import planarloc.robust.absolute_pose as absolute_pose  # noqa: E402
from planarloc.robust.options import RansacOptions, parse_method  # noqa: E402

# The stages of one estimate: (owner, attribute, label). Each is timed at its outermost call, so
# the searches and judgements inside the 6DoF check of a planar pose and inside the second search
# of a weak one count as those stages, not as "searches" or "judgement".
STAGES = (
    (absolute_pose, "_prepare", "set-up (validation, flattening, gravity)"),
    (absolute_pose._Estimation, "_checked_planar", "6DoF check of a planar pose"),
    (absolute_pose._Estimation, "_second_search", "second search of a weak pose"),
    (absolute_pose, "_search", "searches (RANSAC + final refinement)"),
    (absolute_pose, "judge_pose", "judgement (uncertainty and checks)"),
)


class KernelClock:
    """Wraps every compiled kernel of the loaded planarloc modules with a timer counted only at
    the outermost call (a kernel calling a kernel from Python, as the five-point drivers do,
    counts once); ``stage`` names the stage a call belongs to."""

    def __init__(self, record_args: bool = False) -> None:
        self.seconds: Counter[str] = Counter()
        self.calls: Counter[str] = Counter()
        self.by_stage: Counter[str] = Counter()
        self.stage = "other"
        self._depth = 0
        self._wrapped: dict[int, Callable] = {}
        # Every call from Python, nested ones included (each pays numba's dispatch), and the
        # arguments of each kernel's first call (a copy, with ``record_args``), for
        # :func:`dispatch_costs`.
        self.record_args = record_args
        self.dispatches: Counter[str] = Counter()
        self.kernels: dict[str, CPUDispatcher] = {}
        self.first_args: dict[str, tuple[tuple, dict]] = {}

    def _wrap(self, kernel: CPUDispatcher) -> Callable:
        name = f"{kernel.py_func.__module__.removeprefix('planarloc.')}:{kernel.__name__}"

        def timed(*args, **kwargs):
            self.dispatches[name] += 1
            if self.record_args and name not in self.first_args:
                self.kernels[name] = kernel
                self.first_args[name] = copy.deepcopy((args, kwargs))
            if self._depth:
                return kernel(*args, **kwargs)
            self._depth += 1
            t0 = time.process_time()
            try:
                return kernel(*args, **kwargs)
            finally:
                dt = time.process_time() - t0
                self._depth -= 1
                self.seconds[name] += dt
                self.calls[name] += 1
                self.by_stage[self.stage] += dt

        return timed

    def install(self) -> int:
        """Replace the kernels in every loaded planarloc module's namespace (and the kernels the
        five-point solvers hold in closures); returns how many kernels were wrapped."""
        for module in [m for name, m in sys.modules.items() if name.startswith("planarloc.")]:
            for attr, value in list(vars(module).items()):
                if isinstance(value, CPUDispatcher):
                    timed = self._wrapped.setdefault(id(value), self._wrap(value))
                    setattr(module, attr, timed)
                elif isinstance(value, functools.partial) and isinstance(value.func, CPUDispatcher):
                    timed = self._wrapped.setdefault(id(value.func), self._wrap(value.func))
                    setattr(module, attr, functools.partial(timed, *value.args, **value.keywords))
            wrappers = {id(w) for w in self._wrapped.values()}
            for value in list(vars(module).values()):
                if id(value) in wrappers:
                    continue
                cells = getattr(value, "__closure__", None) or ()
                for cell in cells:
                    inner = cell.cell_contents
                    if isinstance(inner, CPUDispatcher):
                        cell.cell_contents = self._wrapped.setdefault(id(inner), self._wrap(inner))
        return len(self._wrapped)


def _loop_seconds(fn: Callable, args: tuple, reps: int) -> float:
    """Best of 5 wall times of ``reps`` calls ``fn(*args)``, per call."""
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn(*args)
        best = min(best, (time.perf_counter() - t0) / reps)
    return best


def dispatch_costs(clock: KernelClock, reps: int = 2000) -> dict[str, float]:
    """Seconds of numba's dispatch per call of each kernel: its first call's arguments timed
    through the dispatcher (type fingerprints, overload resolution, then the compiled wrapper)
    and through the compiled wrapper of the matching overload directly (``entry_point``: it
    unboxes the arguments and boxes the result, as the dispatcher's path does); the difference,
    best of 5 runs each. Kernels whose call leaves arguments to their defaults (numba types
    those as omitted) are left out."""
    out = {}
    for name, (args, kwargs) in clock.first_args.items():
        kernel = clock.kernels[name]
        bound = inspect.signature(kernel.py_func).bind(*args, **kwargs)
        if len(bound.args) < len(inspect.signature(kernel.py_func).parameters):
            continue
        call_args = copy.deepcopy(bound.args)
        entry = kernel.overloads.get(tuple(kernel.typeof_pyval(a) for a in call_args))
        if entry is None:
            continue
        through = _loop_seconds(kernel, call_args, reps)
        direct = _loop_seconds(entry.entry_point, call_args, reps)
        out[name] = max(through - direct, 0.0)
    return out


def report_dispatch(clock: KernelClock, n: int, peer: float) -> dict:
    """Print and return numba's dispatch time per scene (:func:`dispatch_costs`); ``n`` scenes,
    ``peer`` PoseLib's seconds on them."""
    costs = dispatch_costs(clock)
    calls = {k: clock.dispatches[k] / n for k in costs}
    per_scene = sum(costs[k] * calls[k] for k in costs)
    all_calls = sum(clock.dispatches.values()) / n
    per_call = sorted(costs.values()) or [math.nan]
    print(
        f"\nnumba's dispatch: {all_calls:.1f} kernel calls per scene, "
        f"{sum(calls.values()):.1f} of them timed; "
        f"{1e6 * per_call[len(per_call) // 2]:.2f} µs per call (median of {len(costs)} kernels, "
        f"{1e6 * per_call[0]:.2f}-{1e6 * per_call[-1]:.2f}): {1e3 * per_scene:.3f} ms per scene, "
        f"{per_scene * n / peer:.2f} of PoseLib's time"
    )
    for name in sorted(costs, key=lambda k: -costs[k] * calls[k])[:8]:
        print(f"  {1e6 * costs[name]:6.2f} µs x {calls[name]:5.2f} calls  {name}")
    return {
        "ms_per_scene": 1e3 * per_scene,
        "calls_per_scene": all_calls,
        "kernels": {k: {"us_per_call": 1e6 * costs[k], "calls": calls[k]} for k in costs},
    }


def staged(clock: KernelClock, owner: ModuleType | type, attr: str, label: str, totals: Counter[str]) -> None:
    """Time ``owner.attr`` (a module's function or a class's method) as the stage ``label``
    (outermost call only)."""
    fn = getattr(owner, attr)

    def timed(*args, **kwargs):
        if clock.stage != "other":
            return fn(*args, **kwargs)
        clock.stage = label
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            totals[label] += time.process_time() - t0
            clock.stage = "other"

    setattr(owner, attr, timed)


def scenes(seed: int, trials: int) -> list[tuple]:
    """The hard protocol's scenes: (scene, RANSAC seed) for every cell."""
    matches = rb.PROTOCOLS["hard"][2]
    return [
        rb.trial_scene("hard", seed, mi, ri, trial)
        for mi in range(len(matches))
        for ri in range(len(rb.OUTLIERS))
        for trial in range(trials)
    ]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--method", default="auto", help="estimator method (default: %(default)s)")
    p.add_argument("--no-cross-check", action="store_true", help="cross_check=False (bare 2p1p)")
    p.add_argument("--trials", type=int, default=60, help="scenes per cell, 10 cells (default: %(default)s)")
    p.add_argument("--seed", type=int, default=60, help="base seed (default: %(default)s)")
    p.add_argument("--top", type=int, default=12, help="kernels listed (default: %(default)s)")
    p.add_argument(
        "--dispatch",
        action="store_true",
        help="also time numba's dispatch per kernel call (its first call's arguments, through the "
        "dispatcher and through the compiled wrapper directly)",
    )
    p.add_argument("--json", type=Path, help="write the split here")
    args = p.parse_args(argv)
    if args.trials < 1:
        p.error("--trials must be >= 1")
    try:
        parse_method(args.method)
    except ValueError as exc:
        p.error(f"--method: {exc}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    work = scenes(args.seed, args.trials)
    n = len(work)

    def options(seed: int) -> RansacOptions:
        return replace(rb.paper_options(rb.THRESHOLD_PX, seed), cross_check=not args.no_cross_check)

    def ours(sc, seed: int) -> None:
        absolute_pose.estimate_absolute_pose(sc.query_camera, sc.pairs, args.method, options(seed))

    def theirs(sc, seed: int) -> None:
        estimate_query_pose_poselib(
            sc.query_camera, sc.pairs, iterations=rb.ITERATIONS, threshold_px=rb.THRESHOLD_PX, seed=seed
        )

    def run_ours() -> float:
        t0 = time.process_time()
        for sc, seed in work:
            ours(sc, seed)
        return time.process_time() - t0

    print(f"[estimator_profile] {n} scenes, {args.method}, warming up ...", file=sys.stderr)
    rb.warm_up()
    run_ours()  # every kernel loaded, caches warm
    # Back to back per scene, as robustness.py times them: both share the scene's cache state.
    plain = peer = 0.0
    for sc, seed in work:
        t0 = time.process_time()
        ours(sc, seed)
        t1 = time.process_time()
        theirs(sc, seed)
        plain += t1 - t0
        peer += time.process_time() - t1

    clock = KernelClock(record_args=args.dispatch)
    wrapped = clock.install()
    stage_totals: Counter[str] = Counter()
    for owner, attr, label in STAGES:
        staged(clock, owner, attr, label, stage_totals)
    total = run_ours()
    stage_totals["other"] = total - sum(stage_totals.values())
    in_kernels = sum(clock.seconds.values())

    def ms(x: float) -> float:
        return 1e3 * x / n

    print(
        f"\n{args.method}{' (cross_check=False)' if args.no_cross_check else ''}: "
        f"{ms(plain):.3f} ms per scene "
        f"uninstrumented, PoseLib {ms(peer):.3f} ms: ratio {plain / peer:.2f}"
    )
    print(
        f"instrumented {ms(total):.3f} ms ({wrapped} kernels wrapped): in kernels {ms(in_kernels):.3f} ms "
        f"({in_kernels / total:.0%}), Python and numpy around them {ms(total - in_kernels):.3f} ms "
        f"({1 - in_kernels / total:.0%})"
    )
    print("\nper stage (ms per scene; share of PoseLib's time):")
    print(f"  {'stage':44s} {'total':>7s} {'kernels':>8s} {'Python':>7s} {'ratio':>6s}")
    rows = {}
    for label in [s[2] for s in STAGES] + ["other"]:
        k = clock.by_stage[label]
        t = stage_totals[label]
        rows[label] = {"total_ms": ms(t), "kernels_ms": ms(k), "python_ms": ms(t - k), "ratio": t / peer}
        print(f"  {label:44s} {ms(t):7.3f} {ms(k):8.3f} {ms(t - k):7.3f} {t / peer:6.2f}")
    print(f"\nthe {args.top} kernels taking most time (ms per scene, calls per scene):")
    for name, s in clock.seconds.most_common(args.top):
        print(f"  {ms(s):7.4f}  {clock.calls[name] / n:5.2f}  {name}")
    dispatch = report_dispatch(clock, n, peer) if args.dispatch else None
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "method": args.method,
                    "cross_check": not args.no_cross_check,
                    "scenes": n,
                    "seed": args.seed,
                    "ms_per_scene": ms(plain),
                    "poselib_ms_per_scene": ms(peer),
                    "ratio": plain / peer,
                    "instrumented_ms": ms(total),
                    "kernels_ms": ms(in_kernels),
                    "stages": rows,
                    "kernels": {
                        k: {"ms": ms(v), "calls": clock.calls[k] / n} for k, v in clock.seconds.items()
                    },
                    "dispatch": dispatch,
                },
                indent=1,
            )
        )
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
