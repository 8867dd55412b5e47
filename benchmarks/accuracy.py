"""Accuracy under pixel noise: the paper's Sec. V-A accuracy test (Fig. 5), with PoseLib as a peer.

Noise sigma in {0, 1, ..., 10} px, no outliers, 5 references, exactly 100 RANSAC iterations,
``--trials`` scenes per (noise, matches) cell from :func:`planarloc.synthetic.scenes.make_scene`.

Our reading of the paper's "total feature matches 100 / 50 / 10": matches **per reference
pair** (``matches_per_pair`` = 100 / 50 / 10, i.e. 500 / 250 / 50 matches per query with 5
references). The robustness test names the same groups "pairs of matching points" per panel
and needs 20 per pair so that 8p8p still finds 8 inliers in one pair at 60 % outliers; with 10
*total* matches (2 per pair) no baseline could run at all.

Errors (means over the trials, as in Fig. 5; medians are in the JSON):

* rotation: angle of ``R_est R_gtᵀ`` in degrees;
* translation direction: for each reference, the angle between the estimated and the true
  direction of the relative translation ``ref_from_query`` (the ``t̃`` an essential matrix
  gives), averaged over the 5 references. The paper's formula uses the direction of ``t``; of
  the absolute ``cam_from_world`` translation that would depend on the world origin, so we
  take the relative one, which is what panels (d)-(f) evaluate (essential-matrix accuracy);
* position: distance of the camera centres in metres (``pose_errors``).

Inlier threshold: 2 px (Sampson; PoseLib's ``max_epipolar_error``) at every noise level by
default, as in the robustness test. At sigma >> 2 px most true matches then fall outside the
threshold, and the 2 deg Rcheck / consistency checks reject many 6DoF baseline hypotheses, so the
baselines fail more often (``failed``). ``--threshold-scale K`` uses ``max(2 px, K sigma)`` instead.

Every estimate ends with our 6DoF refinement over its inliers (and PoseLib's with its own);
when the inlier sets are complete (e.g. ``--threshold-scale 3``) all methods then converge to
nearly the same pose and the table compares inlier selection, not the minimal solvers.
``--no-refine`` (ours: ``refine=False``, no local optimisation; PoseLib: no final bundle
adjustment, its LO-RANSAC refits stay) compares the best RANSAC hypotheses themselves, closer
to the solver comparison of Fig. 5.

A pose flagged ``degenerate_scale`` is still evaluated (``unreliable_pose``; the paper has no
such gate) and counted in ``flagged``; a run without any pose is counted in ``failed`` and left
out of the means.

Usage::

    python benchmarks/accuracy.py --quick --plot accuracy.png
    python benchmarks/accuracy.py --trials 100 --json accuracy.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _trial_runner import parse_trial_args, run_trials  # noqa: E402
from poselib_peer import estimate_query_pose_poselib  # noqa: E402
from robustness import ITERATIONS, THRESHOLD_PX, paper_options  # noqa: E402

from planarloc.geometry.pose import Pose, pose_errors  # noqa: E402
from planarloc.robust.absolute_pose import estimate_absolute_pose  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402
from planarloc.synthetic.scenes import make_scene  # noqa: E402

METHODS = ("2p1p", "2p2p", "5p5p-nister", "5p5p-stewenius", "8p8p")
PEER = "poselib-gen"
NOISES = tuple(float(s) for s in range(11))
MATCHES = (100, 50, 10)
NUM_REFS = 5
METRICS = (
    ("rotation_deg", "rotation error (deg)"),
    ("direction_deg", "translation direction error (deg)"),
    ("position_m", "position error (m)"),
)


def direction_error_deg(est: Pose, truth: Pose, refs: list[Pose]) -> float:
    """Mean over references of the angle between estimated and true ``ref_from_query`` directions."""
    angles = []
    for ref in refs:
        a = (ref @ est.inverse()).t
        b = (ref @ truth.inverse()).t
        c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
        angles.append(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    return float(np.mean(angles))


def errors(est: Pose, truth: Pose, refs: list[Pose]) -> dict:
    dc, dr = pose_errors(est, truth)
    return {"rotation_deg": dr, "direction_deg": direction_error_deg(est, truth, refs), "position_m": dc}


def run_trial(task: tuple[int, int, int, int, tuple[str, ...], bool, float, bool]) -> dict:
    seed, ni, mi, trial, methods, with_peer, threshold_scale, refine = task
    threshold = max(THRESHOLD_PX, threshold_scale * NOISES[ni])
    ss = np.random.SeedSequence([seed, ni, mi, trial])
    ransac_seed = int(ss.generate_state(1)[0])
    sc = make_scene(
        np.random.default_rng(ss),
        num_refs=NUM_REFS,
        matches_per_pair=MATCHES[mi],
        noise_px=NOISES[ni],
        outlier_ratio=0.0,
    )
    refs = [p.ref_pose for p in sc.pairs]
    opts = paper_options(threshold, ransac_seed, refine)
    out: dict = {"cell": (ni, mi), "methods": {}}
    for method in methods:
        try:
            t = time.process_time()
            est = estimate_absolute_pose(sc.query_camera, sc.pairs, method, opts)
            dt = time.process_time() - t
        except Exception as exc:  # reported as a failure, the run goes on
            out["methods"][method] = {"status": f"error: {type(exc).__name__}: {exc}", "time_s": float("nan")}
            continue
        pose = est.pose if est.success else est.unreliable_pose
        r = {"status": est.status, "time_s": dt}
        if pose is not None:
            r.update(errors(pose, sc.query_pose, refs))
        out["methods"][method] = r
    if with_peer:
        peer = estimate_query_pose_poselib(
            sc.query_camera,
            sc.pairs,
            iterations=ITERATIONS,
            threshold_px=threshold,
            seed=ransac_seed,
            refine=refine,
        )
        r = {"status": "success" if peer.pose is not None else "no_pose", "time_s": peer.cpu_s}
        if peer.pose is not None:
            r.update(errors(peer.pose, sc.query_pose, refs))
        out["methods"][PEER] = r
    return out


def warm_up(methods: tuple[str, ...] = METHODS) -> None:
    sc = make_scene(np.random.default_rng(12345), num_refs=3, matches_per_pair=20, noise_px=1.0)
    for method in methods:
        estimate_absolute_pose(
            sc.query_camera, sc.pairs, method, RansacOptions(max_iterations=20, min_iterations=20)
        )
    estimate_query_pose_poselib(sc.query_camera, sc.pairs, iterations=20)


def run(
    trials: int,
    seed: int,
    jobs: int,
    methods: tuple[str, ...],
    with_peer: bool,
    threshold_scale: float = 0.0,
    refine: bool = True,
) -> list[dict]:
    tasks = [
        (seed, ni, mi, k, methods, with_peer, threshold_scale, refine)
        for k in range(trials)
        for ni in range(len(NOISES))
        for mi in range(len(MATCHES))
    ]
    return run_trials("accuracy", tasks, run_trial, jobs, lambda: warm_up(methods))


def summarise(results: list[dict], names: tuple[str, ...]) -> dict:
    """summary[name][metric]['mean'|'median'][matches][noise index], plus failed/flagged counts."""
    out: dict = {}
    for name in names:
        s: dict = {k: {"mean": {}, "median": {}} for k, _ in METRICS}
        s["failed"], s["flagged"], s["median_time_s"] = {}, {}, {}
        for mi, m in enumerate(MATCHES):
            for key, _ in METRICS:
                s[key]["mean"][m], s[key]["median"][m] = [], []
            s["failed"][m], s["flagged"][m], s["median_time_s"][m] = [], [], []
            for ni in range(len(NOISES)):
                rs = [
                    r["methods"][name]
                    for r in results
                    if tuple(r["cell"]) == (ni, mi) and name in r["methods"]
                ]
                ok = [r for r in rs if "position_m" in r]
                for key, _ in METRICS:
                    vals = [r[key] for r in ok]
                    s[key]["mean"][m].append(float(np.mean(vals)) if vals else float("nan"))
                    s[key]["median"][m].append(float(np.median(vals)) if vals else float("nan"))
                s["failed"][m].append(len(rs) - len(ok))
                s["flagged"][m].append(sum(r["status"] != "success" for r in ok))
                times = [r["time_s"] for r in rs if np.isfinite(r["time_s"])]
                s["median_time_s"][m].append(float(np.median(times)) if times else float("nan"))
        out[name] = s
    return out


def print_tables(
    summary: dict, names: tuple[str, ...], trials: int, threshold_scale: float = 0.0, refine: bool = True
) -> None:
    w = max(len(n) for n in names) + 2
    head = "".join(f"{s:>8g}" for s in NOISES)
    th = f"{THRESHOLD_PX:g} px"
    if threshold_scale > 0:
        th = f"max({th}, {threshold_scale:g} sigma)"
    print(
        f"\nAccuracy: mean errors over {trials} trials per cell; {NUM_REFS} refs, no outliers, "
        f"{ITERATIONS} fixed iterations, inlier threshold {th}, "
        f"{'with' if refine else 'without'} final refinement; columns = noise sigma (px)"
    )
    for key, title in METRICS:
        for m in MATCHES:
            print(f"\n  {title}, {m} matches/pair\n  {'method':<{w}}{head}")
            for name in names:
                vals = summary[name][key]["mean"][m]
                fmt = (lambda v: f"{v:>8.4f}") if key == "position_m" else (lambda v: f"{v:>8.3f}")
                print(f"  {name:<{w}}" + "".join(fmt(v) for v in vals))
    bad = {
        (n, m): (sum(summary[n]["failed"][m]), sum(summary[n]["flagged"][m])) for n in names for m in MATCHES
    }
    if any(f or g for f, g in bad.values()):
        print(
            "\n  runs without a pose (failed, left out of the means) / with a pose flagged "
            "degenerate_scale (included):"
        )
        for (n, m), (f, g) in bad.items():
            if f or g:
                print(f"    {n:<{w}} {m:>3d}/pair: failed {f}, flagged {g} of {trials * len(NOISES)}")


def plot(summary: dict, names: tuple[str, ...], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(METRICS), len(MATCHES), figsize=(4 * len(MATCHES), 3.2 * len(METRICS)), squeeze=False
    )
    for row, (key, title) in enumerate(METRICS):
        for col, m in enumerate(MATCHES):
            ax = axes[row, col]
            for name in names:
                ax.plot(NOISES, summary[name][key]["mean"][m], marker="o", ms=3, label=name)
            ax.set_title(f"{m} matches/pair", fontsize=9)
            ax.set_xlabel("noise sigma (px)")
            ax.set_ylabel(title)
            ax.set_ylim(bottom=0.0)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--trials", type=int, default=100, help="scenes per (noise, matches) cell (default 100)")
    ap.add_argument("--quick", action="store_true", help="20 trials per cell")
    ap.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    ap.add_argument("--json", type=Path, help="write the summary (means and medians) to this file")
    ap.add_argument("--plot", type=Path, help="save a Fig. 5-style plot (PNG) to this file")
    ap.add_argument(
        "--threshold-scale",
        type=float,
        default=0.0,
        metavar="K",
        help="inlier threshold max(2 px, K * sigma) instead of a fixed 2 px (default 0: fixed)",
    )
    ap.add_argument(
        "--no-refine",
        action="store_true",
        help="evaluate the best RANSAC hypothesis: no local optimisation or final refinement",
    )
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    plan = parse_trial_args(ap, argv, PEER)
    if plan is None:
        return 1
    args, trials, methods, names = plan.args, plan.trials, plan.methods, plan.names
    t0 = time.perf_counter()
    results = run(
        trials, args.seed, args.jobs, methods, not args.no_poselib, args.threshold_scale, not args.no_refine
    )
    wall = time.perf_counter() - t0
    summary = summarise(results, names)
    print_tables(summary, names, trials, args.threshold_scale, not args.no_refine)
    w = max(len(n) for n in names) + 2
    print("\nMedian CPU time per query (ms), by matches/pair:")
    for name in names:
        print(
            f"  {name:<{w}}"
            + "".join(f"{m:>5d}: {1e3 * np.median(summary[name]['median_time_s'][m]):7.2f}" for m in MATCHES)
        )
    print(f"\nWall time {wall:.0f} s with {args.jobs} job(s), warm-up included")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {
                    "protocol": {
                        "num_refs": NUM_REFS,
                        "noises_px": NOISES,
                        "matches_per_pair": MATCHES,
                        "iterations": ITERATIONS,
                        "threshold_px": THRESHOLD_PX,
                        "threshold_scale": args.threshold_scale,
                        "refine": not args.no_refine,
                        "trials": trials,
                        "seed": args.seed,
                    },
                    "wall_time_s": wall,
                    "summary": summary,
                },
                indent=1,
            )
        )
        print(f"wrote {args.json}", file=sys.stderr)
    if args.plot:
        plot(summary, names, args.plot)
        print(f"wrote {args.plot}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
