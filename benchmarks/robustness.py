"""Robustness to outliers: the paper's Sec. V-A protocol (Fig. 6), with PoseLib as a peer.

For matches per pair in {100, 50, 20} and outlier rates in {0, 20, 40, 50, 60} %, ``--trials``
scenes are drawn with :func:`planarloc.synthetic.scenes.make_scene` (5 references, 1 px noise,
f = 800, 1280x1080, points in [-10, 10]^3, planar cameras). On each scene every method runs
with exactly 100 RANSAC iterations (``min_iterations = max_iterations = 100``), and so does
PoseLib's ``estimate_generalized_relative_pose`` (rig 1 = the query, rig 2 = the posed
references; see ``poselib_peer.py``). Success = camera-centre error < 0.1 m and rotation
error < 1 deg; a pose we report as unreliable (``degenerate_scale``) or no pose is a failure.

Timing: each call is timed in the worker process that ran it, ours and PoseLib's on the same
scene back to back, after a warm-up in the parent process (numba compiled or loaded from its
cache, inherited by the forked workers). Both wall time (``perf_counter``) and CPU time of the
process (``process_time``; numba and PoseLib are single-threaded) are recorded; on a machine
shared with other jobs the CPU time is the meaningful one. With ``--jobs 2`` two workers share
the machine's two cores; ``--jobs 1`` gives the cleanest wall times.

``--protocol hard`` (issue 10): 3 references, 1.5 px noise, 50 and 20 matches per pair, the same
outlier rates; everything else as above. ``2p1p-oracle`` is 2p1p fed only the true inliers of
each scene (the limit of outlier rejection for that estimator).

Usage::

    python benchmarks/robustness.py                 # 100 trials per cell, as the paper
    python benchmarks/robustness.py --protocol hard --methods 2p1p 2p2p 2p1p-oracle --trials 50
    python benchmarks/robustness.py --quick         # 20 trials per cell
    python benchmarks/robustness.py --trials 50 --seed 3 --json out.json --jobs 1
    python benchmarks/robustness.py --protocol hard --methods 2p1p auto --iterations 10 --no-poselib
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _trial_runner import parse_trial_args, run_trials  # noqa: E402
from poselib_peer import estimate_query_pose_poselib  # noqa: E402

from planarloc.geometry.pose import pose_errors  # noqa: E402
from planarloc.robust.absolute_pose import estimate_absolute_pose  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402
from planarloc.robust.pair_matches import PairMatches  # noqa: E402
from planarloc.synthetic.scenes import SyntheticScene, make_scene  # noqa: E402

METHODS = ("2p1p", "2p2p", "5p5p-nister", "5p5p-stewenius", "8p8p")
ORACLE = "2p1p-oracle"  # 2p1p on the true inliers only
# The library's defaults (issue 17): "auto", and "2p1p" with its cross-check (the paper's methods
# above run without it); "auto-oracle" is auto on the true inliers only.
DEFAULTS = {
    "auto": ("auto", True, False),
    "2p1p-checked": ("2p1p", True, False),
    "auto-oracle": ("auto", True, True),
}
CHOICES = METHODS + (ORACLE,) + tuple(DEFAULTS)
PEER = "poselib-gen"
OUTLIERS = (0.0, 0.2, 0.4, 0.5, 0.6)
# name: (references, pixel noise, matches per pair)
PROTOCOLS = {"paper": (5, 1.0, (100, 50, 20)), "hard": (3, 1.5, (50, 20))}
NUM_REFS, NOISE_PX, MATCHES = PROTOCOLS["paper"]
ITERATIONS = 100
MAX_CENTRE_ERROR_M = 0.1
MAX_ROTATION_ERROR_DEG = 1.0
THRESHOLD_PX = 2.0  # ours (RansacOptions default) and PoseLib's max_epipolar_error


def trial_seeds(seed: int, mi: int, ri: int, trial: int) -> tuple[np.random.Generator, int]:
    """Scene generator and RANSAC seed of one trial, independent of scheduling."""
    ss = np.random.SeedSequence([seed, mi, ri, trial])
    return np.random.default_rng(ss), int(ss.generate_state(1)[0])


def trial_scene(protocol: str, seed: int, mi: int, ri: int, trial: int) -> tuple[SyntheticScene, int]:
    """The scene of one trial of ``protocol`` (``matches[mi]`` per pair, ``OUTLIERS[ri]``) and its
    RANSAC seed, from :func:`trial_seeds`: the scenes every hard-protocol benchmark shares."""
    num_refs, noise_px, matches = PROTOCOLS[protocol]
    rng, ransac_seed = trial_seeds(seed, mi, ri, trial)
    sc = make_scene(
        rng, num_refs=num_refs, matches_per_pair=matches[mi], noise_px=noise_px, outlier_ratio=OUTLIERS[ri]
    )
    return sc, ransac_seed


def inlier_pairs(sc) -> list[PairMatches]:
    """The scene's pairs without their outliers (the oracle's input)."""
    return [
        PairMatches(
            p.ref_pose,
            p.ref_camera,
            p.query_points[~o],
            p.ref_points[~o],
            None if p.query_indices is None else p.query_indices[~o],
        )
        for p, o in zip(sc.pairs, sc.is_outlier)
    ]


def paper_options(
    threshold_px: float, seed: int, refine: bool = True, iterations: int = ITERATIONS
) -> RansacOptions:
    """The paper's methods as published: exactly ``iterations`` (the paper's ``ITERATIONS``) RANSAC
    iterations, no structure and no 6DoF cross-check of the planar pose (the library's default
    cross_check=True adds one 5-point search per query; see BENCHMARKS.md, "Trust")."""
    return RansacOptions(
        max_iterations=iterations,
        min_iterations=iterations,
        threshold_px=threshold_px,
        seed=seed,
        refine=refine,
        structure="none",
        cross_check=False,
    )


def run_trial(task: tuple[int, int, int, int, tuple[str, ...], bool, str, int]) -> dict:
    """One scene, every method and the peer on it. Returns errors, status and time per method."""
    seed, mi, ri, trial, methods, with_peer, protocol, iterations = task
    c0 = time.process_time()
    sc, ransac_seed = trial_scene(protocol, seed, mi, ri, trial)
    out: dict = {"cell": (mi, ri), "scene_cpu_s": time.process_time() - c0, "methods": {}}
    opts = paper_options(THRESHOLD_PX, ransac_seed, iterations=iterations)
    for method in methods:
        name, checked, oracle = DEFAULTS.get(
            method, ("2p1p" if method == ORACLE else method, False, method == ORACLE)
        )
        o = replace(opts, cross_check=checked)
        try:
            t, c = time.perf_counter(), time.process_time()
            est = estimate_absolute_pose(sc.query_camera, inlier_pairs(sc) if oracle else sc.pairs, name, o)
            dt, dc = time.perf_counter() - t, time.process_time() - c
        except Exception as exc:  # a crash is a failure to report, not a reason to lose the run
            out["methods"][method] = {
                "ok": False,
                "status": f"error: {type(exc).__name__}: {exc}",
                "time_s": float("nan"),
                "cpu_s": float("nan"),
                "trace": traceback.format_exc(),
            }
            continue
        r = {"status": est.status, "time_s": dt, "cpu_s": dc, "stage_s": dict(est.stats.time_s), "ok": False}
        pose = est.pose if est.success else est.unreliable_pose
        if pose is not None:
            dc, dr = pose_errors(pose, sc.query_pose)
            good = dc < MAX_CENTRE_ERROR_M and dr < MAX_ROTATION_ERROR_DEG
            # A success promises the centre within its reported std (benchmarks/trust.py: 3σ + 5 cm).
            broken = bool(est.success and dc > 3.0 * est.position_std_m + 0.05)
            r.update(
                centre_m=dc,
                rotation_deg=dr,
                ok=bool(est.success and good),
                gated_correct=bool(not est.success and good),
                wrong_success=bool(est.success and not good),
                broken_promise=broken,
            )
        out["methods"][method] = r
    if with_peer:
        peer = estimate_query_pose_poselib(
            sc.query_camera, sc.pairs, iterations=iterations, threshold_px=THRESHOLD_PX, seed=ransac_seed
        )
        r = {
            "status": "success" if peer.pose is not None else "no_pose",
            "time_s": peer.time_s,
            "cpu_s": peer.cpu_s,
            "ok": False,
        }
        if peer.pose is not None:
            dc, dr = pose_errors(peer.pose, sc.query_pose)
            good = dc < MAX_CENTRE_ERROR_M and dr < MAX_ROTATION_ERROR_DEG
            r.update(
                centre_m=dc, rotation_deg=dr, ok=bool(good), wrong_success=not good
            )  # PoseLib reports no failure
        out["methods"][PEER] = r
    return out


def warm_up(methods: tuple[str, ...] = METHODS) -> None:
    """Load the numba caches (or compile) of every method and every verification path before
    anything is timed (several scenes: some paths run only on some scenes)."""
    for k in range(12):
        sc = make_scene(
            np.random.default_rng(12345 + k),
            num_refs=3,
            matches_per_pair=20,
            noise_px=1.5,
            outlier_ratio=0.2 + 0.04 * k,
        )
        for method in methods:
            name, checked, _ = DEFAULTS.get(method, ("2p1p" if method == ORACLE else method, False, False))
            estimate_absolute_pose(
                sc.query_camera,
                sc.pairs,
                name,
                RansacOptions(max_iterations=100, min_iterations=100, structure="none", cross_check=checked),
            )
    estimate_query_pose_poselib(sc.query_camera, sc.pairs, iterations=20)


def run(
    trials: int,
    seed: int,
    jobs: int,
    methods: tuple[str, ...],
    with_peer: bool,
    protocol: str = "paper",
    iterations: int = ITERATIONS,
) -> list[dict]:
    matches = PROTOCOLS[protocol][2]
    tasks = [
        (seed, mi, ri, k, methods, with_peer, protocol, iterations)
        for k in range(trials)
        for mi in range(len(matches))
        for ri in range(len(OUTLIERS))
    ]
    return run_trials("robustness", tasks, run_trial, jobs, lambda: warm_up(methods))


def summarise(results: list[dict], names: tuple[str, ...], protocol: str = "paper") -> dict:
    """Per cell and method: success rate, median time, status counts, median errors."""
    cells: dict = {}
    for mi, m in enumerate(PROTOCOLS[protocol][2]):
        for ri, r in enumerate(OUTLIERS):
            rows = [res for res in results if tuple(res["cell"]) == (mi, ri)]
            cell = {
                "matches_per_pair": m,
                "outlier_ratio": r,
                "trials": len(rows),
                "scene_median_cpu_s": float(np.median([x["scene_cpu_s"] for x in rows])),
                "methods": {},
            }
            for name in names:
                rs = [x["methods"][name] for x in rows if name in x["methods"]]
                times = [v["time_s"] for v in rs if np.isfinite(v["time_s"])]
                cpus = [v["cpu_s"] for v in rs if np.isfinite(v["cpu_s"])]
                centre = [v["centre_m"] for v in rs if "centre_m" in v]
                stage_keys = sorted({k for v in rs for k in v.get("stage_s", {})})
                cell["methods"][name] = {
                    "success_rate": float(np.mean([v["ok"] for v in rs])) if rs else float("nan"),
                    "median_time_s": float(np.median(times)) if times else float("nan"),
                    "median_cpu_s": float(np.median(cpus)) if cpus else float("nan"),
                    "mean_cpu_s": float(np.mean(cpus)) if cpus else float("nan"),
                    "mean_time_s": float(np.mean(times)) if times else float("nan"),
                    "median_centre_error_m": float(np.median(centre)) if centre else None,
                    "status": dict(Counter(v["status"] for v in rs)),
                    "gated_but_correct": int(sum(v.get("gated_correct", False) for v in rs)),
                    "wrong_successes": int(sum(v.get("wrong_success", False) for v in rs)),
                    "broken_promises": int(sum(v.get("broken_promise", False) for v in rs)),
                    "median_stage_s": {
                        k: float(np.median([v["stage_s"].get(k, 0.0) for v in rs])) for k in stage_keys
                    },
                    "mean_stage_s": {
                        k: float(np.mean([v["stage_s"].get(k, 0.0) for v in rs])) for k in stage_keys
                    },
                }
            cells[f"{m}x{r:.1f}"] = cell
    return cells


def cells_ratio(cells: dict, matches: int | None, name: str) -> float:
    """Mean CPU time of ``name`` over the mean CPU time of the peer, over the cells of ``matches``
    matches per pair (all cells when None), weighting each cell by its trials."""
    keys = [k for k, c in cells.items() if matches is None or c["matches_per_pair"] == matches]
    ours = sum(cells[k]["methods"][name]["mean_cpu_s"] * cells[k]["trials"] for k in keys)
    peer = sum(cells[k]["methods"][PEER]["mean_cpu_s"] * cells[k]["trials"] for k in keys)
    return ours / peer if peer > 0 else float("nan")


def print_tables(
    cells: dict, names: tuple[str, ...], trials: int, protocol: str = "paper", iterations: int = ITERATIONS
) -> None:
    num_refs, noise_px, matches = PROTOCOLS[protocol]
    w = max(len(n) for n in names) + 2
    head = "".join(f"{int(100 * r):>6d}%" for r in OUTLIERS)

    def per_cell(rows: Sequence[str], cell: Callable[[dict], str]) -> None:
        """A table per matches/pair: a row per method of ``rows``, a column per outlier rate."""
        for m in matches:
            print(f"\n  matches/pair = {m}\n  {'method':<{w}}{head}")
            for name in rows:
                vals = "".join(cell(cells[f"{m}x{r:.1f}"]["methods"][name]) for r in OUTLIERS)
                print(f"  {name:<{w}}{vals}")

    print(
        f"\nSuccess rate (%), protocol {protocol!r}: {num_refs} refs, {noise_px:g} px noise, {iterations} "
        f"fixed iterations, centre < {MAX_CENTRE_ERROR_M} m & R < {MAX_ROTATION_ERROR_DEG} deg, "
        f"{trials} trials per cell"
    )
    per_cell(names, lambda c: f"{100 * c['success_rate']:>7.0f}")
    print(
        f"\nWrong successes (reported a pose, but centre >= {MAX_CENTRE_ERROR_M} m or R >= "
        f"{MAX_ROTATION_ERROR_DEG} deg), count per cell of {trials}:"
    )
    per_cell(names, lambda c: f"{c['wrong_successes']:>7d}")
    ours = [n for n in names if n != PEER]
    print(
        "\nBroken promises (success with centre error > 3 x its position_std_m + 5 cm), count per cell of "
        f"{trials}:"
    )
    per_cell(ours, lambda c: f"{c['broken_promises']:>7d}")
    for key, label in (("median_cpu_s", "CPU"), ("median_time_s", "wall")):
        print(f"\nMedian {label} time per query (ms), by matches/pair (median of the per-cell medians):")
        print(f"  {'method':<{w}}" + "".join(f"{m:>8d}" for m in matches))
        for name in names:
            vals = [
                np.median([cells[f"{m}x{r:.1f}"]["methods"][name][key] for r in OUTLIERS]) for m in matches
            ]
            print(f"  {name:<{w}}" + "".join(f"{1e3 * v:>8.2f}" for v in vals))
    for m in matches if PEER in names and "2p1p" in names else ():
        print(f"\nTime ratio ours/PoseLib, 2p1p vs {PEER}, {num_refs}x{m} matches (median per query):")
        print(
            f"  {'outliers':<10}{'CPU ours':>10}{'PoseLib':>10}{'ratio':>7}"
            f"{'wall ours':>11}{'PoseLib':>10}{'ratio':>7}"
        )
        for r in OUTLIERS:
            c = cells[f"{m}x{r:.1f}"]["methods"]
            a, b = c["2p1p"], c[PEER]
            print(
                f"  {int(100 * r):>3d}%      {1e3 * a['median_cpu_s']:>8.2f}ms"
                f"{1e3 * b['median_cpu_s']:>8.2f}ms"
                f"{a['median_cpu_s'] / b['median_cpu_s']:>7.2f}{1e3 * a['median_time_s']:>9.2f}ms"
                f"{1e3 * b['median_time_s']:>8.2f}ms{a['median_time_s'] / b['median_time_s']:>7.2f}"
            )
        for r in (0.0, 0.6):
            st = cells[f"{m}x{r:.1f}"]["methods"]["2p1p"]["median_stage_s"]
            if st:
                print(
                    f"  2p1p stages at {m} matches, {int(100 * r)}% outliers (median wall ms): "
                    + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in st.items())
                )
    if PEER in names:
        print(
            f"\nCPU time per query, ours / {PEER} (ratio of the means over every scene of each matches/pair):"
        )
        print(f"  {'method':<{w}}" + "".join(f"{m:>8d}" for m in matches) + f"{'all':>8}")
        for name in ours:
            vals = [cells_ratio(cells, m, name) for m in matches]
            print(
                f"  {name:<{w}}"
                + "".join(f"{v:>8.2f}" for v in vals)
                + f"{cells_ratio(cells, None, name):>8.2f}"
            )
    if PEER in names:
        # Where the time goes: the search (setup, hypotheses, scoring, local optimisation, final
        # refinement) and the checks that make a success a promise (verification; the cross-check
        # search of a planar pose): each part's share of our wall time per query, applied to the
        # CPU ratio above (wall-clock stage times, CPU-time ratio: robust to a loaded machine).
        print(f"\nThe CPU ratio to {PEER} (all cells) split by part:")
        for name in ours:
            total = sum(c["methods"][name]["mean_time_s"] for c in cells.values())
            st = [c["methods"][name].get("mean_stage_s", {}) for c in cells.values()]
            part = {k: sum(x.get(k, 0.0) for x in st) / total for k in ("verification", "cross_check")}
            search = (
                sum(
                    sum(v for k, v in x.items() if k not in ("verification", "cross_check", "total"))
                    for x in st
                )
                / total
            )
            ratio = cells_ratio(cells, None, name)
            print(
                f"  {name:<{w}}{ratio:.2f} = search {ratio * search:.2f} + verification "
                f"{ratio * part['verification']:.2f} + cross-check {ratio * part['cross_check']:.2f} + other "
                f"{ratio * (1 - search - part['verification'] - part['cross_check']):.2f}"
            )
    errors = {
        n: sum(v for s, v in cells[c]["methods"][n]["status"].items() if s.startswith("error"))
        for c in cells
        for n in names
    }
    if any(errors.values()):
        print(
            f"\nWARNING: methods raised exceptions (counted as failures): "
            f"{ {n: k for n, k in errors.items() if k} }"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--trials", type=int, default=100, help="scenes per (matches, outliers) cell (default 100)"
    )
    ap.add_argument("--quick", action="store_true", help="20 trials per cell")
    ap.add_argument("--seed", type=int, default=0, help="base seed of scenes and RANSAC (default 0)")
    ap.add_argument("--json", type=Path, help="write the per-cell summary to this file")
    ap.add_argument(
        "--jobs",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="worker processes (default: min(2, cores)); 1 for the cleanest timings",
    )
    ap.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        choices=CHOICES,
        help=f"methods to run (default: all but {ORACLE})",
    )
    ap.add_argument(
        "--protocol",
        choices=tuple(PROTOCOLS),
        default="paper",
        help="paper: 5 refs, 1 px, 100/50/20 matches; hard: 3 refs, 1.5 px, 50/20 matches",
    )
    ap.add_argument(
        "--iterations",
        type=int,
        default=ITERATIONS,
        help="fixed RANSAC samples of every method and the peer (default: the paper's %(default)s); "
        "fewer show what a small budget does to success and to promises",
    )
    plan = parse_trial_args(ap, argv, PEER)
    if plan is None:
        return 1
    args, trials, methods, names = plan.args, plan.trials, plan.methods, plan.names
    t0 = time.perf_counter()
    if args.iterations < 1:
        ap.error("--iterations must be >= 1")
    results = run(trials, args.seed, args.jobs, methods, not args.no_poselib, args.protocol, args.iterations)
    wall = time.perf_counter() - t0
    cells = summarise(results, names, args.protocol)
    print_tables(cells, names, trials, args.protocol, args.iterations)
    scene_s = sum(r["scene_cpu_s"] for r in results)
    method_s = {
        n: sum(r["methods"][n]["cpu_s"] for r in results if np.isfinite(r["methods"][n]["cpu_s"]))
        for n in names
    }
    cpu_total = scene_s + sum(method_s.values())
    print(
        f"\nWall time {wall:.0f} s with {args.jobs} job(s), warm-up included. CPU time: scene generation "
        f"{scene_s:.0f} s, estimators "
        + ", ".join(f"{n} {s:.0f} s" for n, s in method_s.items())
        + f"; total {cpu_total:.0f} s = {cpu_total / args.jobs:.0f} s wall on {args.jobs} idle core(s)"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {
                    "protocol": {
                        "name": args.protocol,
                        "num_refs": PROTOCOLS[args.protocol][0],
                        "noise_px": PROTOCOLS[args.protocol][1],
                        "iterations": args.iterations,
                        "threshold_px": THRESHOLD_PX,
                        "success": {"centre_m": MAX_CENTRE_ERROR_M, "rotation_deg": MAX_ROTATION_ERROR_DEG},
                        "trials": trials,
                        "seed": args.seed,
                        "jobs": args.jobs,
                    },
                    "wall_time_s": wall,
                    "scene_generation_cpu_s": scene_s,
                    "estimator_cpu_s": method_s,
                    "cells": cells,
                },
                indent=1,
            )
        )
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
