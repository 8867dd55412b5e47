"""The tail of the position std on the hard protocol: how far past their std ``auto``'s successes
lie, by inlier count, and whether local statistics of the fit single out the broken promises
(issue 31).

Every scene of ``robustness.py --protocol hard`` (3 map images, 50 and 20 matches per pair,
1.5 px noise, 0-60 % outliers, 100 fixed iterations) runs through ``auto``. For each success:

- its error over its std ``z = error / position_std_m``, whose quantiles per inlier band say where
  the std's tail is short (a broken promise is ``error > 3 std + 5 cm``);
- three local statistics of the fit at the pose, on its inliers, with the refinement's Cauchy
  weights ``w`` (scale τ) on its Sampson residuals ``r`` and their Jacobian ``J`` (rotation, centre):
  the model std ``σ̂² (JᵀWJ)⁻¹`` (what the curvature says), the sandwich std
  ``H⁻¹ (Σ w² r² JᵢᵀJᵢ) H⁻¹ · m / (m - 6)`` (heteroscedasticity- and misfit-robust) and the
  jackknife std over single matches (one-step leave-one-out shifts ``H⁻¹ Jᵢᵀ wᵢ rᵢ / (1 - hᵢ)``),
  each the square root of the top eigenvalue of its centre block.

Printed: z quantiles per band; each statistic's ratio to the model std over all successes and for
the broken promises; and what widening every std by that ratio (× ``k``) would do: promises still
broken, successes whose std then passes ``max_position_std_m`` (refused) and the correct ones among
them (0.1 m / 1°). A statistic worth building on keeps many promises for few correct poses.

    python benchmarks/std_tail.py --seeds 102 103 104 105 --jobs 2
    python benchmarks/std_tail.py --seeds 110 --trials 50 --json tail.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import robustness as rb  # noqa: E402
from _trial_runner import run_trials  # noqa: E402

from planarloc.geometry.pose import pose_errors  # noqa: E402
from planarloc.robust.absolute_pose import estimate_absolute_pose  # noqa: E402
from planarloc.robust.problem import build_problem  # noqa: E402
from planarloc.robust.refinement import residuals_jacobian  # noqa: E402

BANDS = ((0, 24), (24, 32), (32, 48), (48, 64), (64, 96), (96, 10_000))  # inliers
WIDEN = (1.0, 1.2, 1.5)  # k in "std x max(1, k x ratio)"


def fit_statistics(J: np.ndarray, r: np.ndarray, loss_scale: float) -> dict[str, float]:
    """Model, sandwich and single-match jackknife stds of the centre (m) from Sampson residuals
    ``r`` (m,) in pixels and their Jacobian ``J`` (m, 6) w.r.t. (rotation increment, centre), at
    a pose refined with the Cauchy loss of scale ``loss_scale`` (pixels); m > 6."""
    m = len(r)
    w = 1.0 / (1.0 + r * r / loss_scale**2)
    H_inv = np.linalg.inv((J * w[:, None]).T @ J)
    sigma_sq = float(np.sum(w * r * r)) / (m - 6)
    meat = (J * (w * w * r * r)[:, None]).T @ J
    sandwich = H_inv @ meat @ H_inv * m / (m - 6)
    leverage = np.einsum("ij,jk,ik->i", J * w[:, None], H_inv, J)
    shifts = (H_inv @ (J * (w * r)[:, None]).T).T[:, 3:] / (1.0 - leverage)[:, None]
    centred = shifts - shifts.mean(axis=0)
    jackknife = (m - 1) / m * centred.T @ centred

    def top_std(cov: np.ndarray) -> float:
        return float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))

    return {
        "model_std": top_std(sigma_sq * H_inv[3:, 3:]),
        "sandwich_std": top_std(sandwich[3:, 3:]),
        "jackknife_std": top_std(jackknife),
    }


def run_trial(task: tuple[int, int, int, int]) -> dict | None:
    """One scene through ``auto``: None unless it succeeds, else its error, std and fit statistics."""
    seed, mi, ri, trial = task
    sc, ransac_seed = rb.trial_scene("hard", seed, mi, ri, trial)
    options = rb.paper_options(rb.THRESHOLD_PX, ransac_seed)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", options)
    if not est.success:
        return None
    centre_m, rotation_deg = pose_errors(est.pose, sc.query_pose)
    prob = build_problem(sc.query_camera, sc.pairs).arrays
    rows = np.flatnonzero(np.concatenate([np.asarray(m, dtype=bool) for m in est.inliers]))
    R, t = np.ascontiguousarray(est.pose.R), np.asarray(est.pose.t, dtype=float)
    r, J = np.empty(len(rows)), np.empty((len(rows), 6))
    none = np.zeros(0, dtype=np.int64)
    residuals_jacobian(R, -R.T @ t, np.eye(3), prob, rows.astype(np.int64), none, r, J, np.empty((0, 3)))
    return {
        "scene": [seed, mi, ri, trial],
        "inliers": int(est.num_inliers),
        "centre_m": float(centre_m),
        "rotation_deg": float(rotation_deg),
        "std_m": float(est.position_std_m),
        "max_std_m": float(options.max_position_std_m),
        **fit_statistics(J, r, options.threshold_px),
    }


def report(rows: list[dict]) -> dict:
    """Print the tables of the module docstring; return them."""
    n, err, std = (np.array([r[k] for r in rows]) for k in ("inliers", "centre_m", "std_m"))
    rot, max_std = np.array([r["rotation_deg"] for r in rows]), rows[0]["max_std_m"]
    broken, correct = err > 3.0 * std + 0.05, (err < 0.1) & (rot < 1.0)
    z = err / std
    out: dict = {"successes": len(rows), "broken": int(broken.sum()), "bands": [], "statistics": {}}
    print(f"\n{len(rows)} successes of auto, {int(broken.sum())} beyond 3 std + 5 cm\n")
    print(
        f"{'inliers':>10} {'successes':>9} {'broken':>6} {'z 50%':>6} {'z 99%':>6} {'z 99.9%':>7} {'std':>6}"
    )
    for lo, hi in BANDS:
        b = (n >= lo) & (n < hi)
        if not b.any():
            continue
        q = np.quantile(z[b], [0.5, 0.99, 0.999])
        label = f"{lo}-{hi - 1}" if hi < 10_000 else f">= {lo}"
        print(
            f"{label:>10} {int(b.sum()):9d} {int(broken[b].sum()):6d} {q[0]:6.2f} {q[1]:6.2f} {q[2]:7.2f} "
            f"{np.median(std[b]):6.3f}"
        )
        out["bands"].append(
            {
                "inliers": [lo, hi],
                "successes": int(b.sum()),
                "broken": int(broken[b].sum()),
                "z_quantiles": q.tolist(),
            }
        )
    model = np.array([r["model_std"] for r in rows])
    print(f"\n{'statistic / model std':>24} {'all: 50%':>8} {'90%':>5} {'99%':>5}   broken promises")
    for key in ("sandwich_std", "jackknife_std"):
        ratio = np.array([r[key] for r in rows]) / model
        q = np.quantile(ratio, [0.5, 0.9, 0.99])
        print(
            f"{key:>24} {q[0]:8.2f} {q[1]:5.2f} {q[2]:5.2f}   "
            + " ".join(f"{x:.2f}" for x in np.sort(ratio[broken]))
        )
        widened = []
        for k in WIDEN:
            new = std * np.maximum(1.0, k * ratio)
            refused = new > max_std
            left = int((~refused & (err > 3.0 * new + 0.05)).sum())
            widened.append(
                {
                    "k": k,
                    "broken_left": left,
                    "refused": int(refused.sum()),
                    "correct_refused": int((refused & correct).sum()),
                }
            )
            print(
                f"{'':>24} widened x {k}: {left} broken left, {int(refused.sum())} refused "
                f"({int((refused & correct).sum())} of them correct)"
            )
        out["statistics"][key] = {
            "ratio_quantiles": q.tolist(),
            "broken_ratios": np.sort(ratio[broken]).tolist(),
            "widened": widened,
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[102], help="base seeds (default: %(default)s)")
    ap.add_argument(
        "--trials", type=int, default=200, help="scenes per cell, 10 cells (default: %(default)s)"
    )
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default: %(default)s)")
    ap.add_argument("--json", type=Path, help="write every success's figures and the tables here")
    args = ap.parse_args(argv)
    if args.trials < 1 or args.jobs < 1:
        ap.error("--trials and --jobs must be >= 1")
    if args.json is not None and not args.json.parent.is_dir():
        ap.error(f"--json: folder {args.json.parent} does not exist")
    tasks = [
        (s, mi, ri, t)
        for s in args.seeds
        for mi in range(2)
        for ri in range(len(rb.OUTLIERS))
        for t in range(args.trials)
    ]
    rows = [
        r for r in run_trials("std_tail", tasks, run_trial, args.jobs, lambda: rb.warm_up(("auto",))) if r
    ]
    if not rows:
        print("error: no success to study; more --trials or --seeds", file=sys.stderr)
        return 1
    tables = report(rows)
    if args.json is not None:
        args.json.write_text(
            json.dumps({"seeds": args.seeds, "trials": args.trials, **tables, "successes_list": rows})
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
