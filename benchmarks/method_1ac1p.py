"""The one-affine-correspondence method ``1ac1p`` against ``2p1p``, end to end (issue 31).

``1ac1p`` draws one match with its local affine frame in a map image j, solves the planar relative
pose from it alone (:func:`planarloc.solvers.relpose_planar_1ac.solve_planar_1ac`, Guan et al.,
CVPR 2020), and takes the scale from the matches of the other map images by consensus, exactly as
the library's consensus ``2p1p`` does after its 2-point stage (:mod:`planarloc.robust.consensus_scale`:
the same candidate ranking on pair j, the same consensus, scoring, local optimisation, final
refinement and judgement). Its minimal sample is 2 matches (one of them an affine
correspondence) against 2p1p's 3, so an adaptive search stops sooner at the same confidence, if
its hypotheses are as good. ``mixed`` gives half of each batch's samples to each generator (the
form a hypothesis generator inside ``auto`` would take).

The scenes are the hard protocol of ``robustness.py`` (3 map images, 1.5 px noise, 50 and 20
matches per image, 0-60 % outliers). The generated scenes carry no image patches, so each match
gets a local affine map ``A = ∂x_ref/∂x_query`` here: for an inlier, that of a surface patch
through the match's point (triangulated from the true poses) with a random normal facing the
query, then one of the frame models below; for an outlier, a random rotation and scale.

Frame models (the noise of ``solvers_1ac.py``: rotation N(0, 1°), scale exp(N(0, 2 %))):
  affine       the true local affine with that noise (an affine-covariant detector's frame);
  similarity   its nearest similarity with that noise (what SIFT's orientation and scale hold).

Budgets: ``fixed`` is the protocol's 100 samples (``min_iterations = max_iterations``);
``adaptive`` stops at 99.99 % confidence (at least 20 hypotheses, at most 1,000 samples), where a
smaller minimal sample pays. Each method runs bare (no 6DoF cross-check) on the same scenes with
the same RANSAC seed, in an order that rotates from scene to scene; CPU time per scene, and
PoseLib's on the same scenes for the ratio.

The ``1ac1p`` estimator lives here, not in the library: it is measured, not shipped (BENCHMARKS.md,
"One affine correspondence"). It enters the library's estimate through ``absolute_pose._estimator``
(the factory of a search's estimator), replaced for the planar family while this script runs.

    python benchmarks/method_1ac1p.py                       # 40 scenes per cell, both budgets
    python benchmarks/method_1ac1p.py --trials 10 --budgets fixed --json 1ac1p.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent))
import robustness as rb  # noqa: E402
from poselib_peer import estimate_query_pose_poselib  # noqa: E402
from solvers_1ac import nearest_similarity, rot2  # noqa: E402

import planarloc.robust.absolute_pose as absolute_pose  # noqa: E402
from planarloc.geometry.epipolar_kernels import sampson_sq  # noqa: E402
from planarloc.geometry.pose import pose_errors  # noqa: E402
from planarloc.robust.consensus_scale import (  # noqa: E402
    RelativeCandidates,
    _keep_distinct,
    hypotheses_2p1p_consensus,
)
from planarloc.robust.estimators import Planar2p1pEstimator  # noqa: E402
from planarloc.robust.hypotheses import DEGENERATE, Hypotheses  # noqa: E402
from planarloc.robust.options import Method, RansacOptions  # noqa: E402
from planarloc.robust.sampling import draw_pair_samples  # noqa: E402
from planarloc.solvers.relpose_planar_1ac import solve_planar_1ac  # noqa: E402
from planarloc.solvers.relpose_planar_2p import planar_pose_into  # noqa: E402

FRAME_ANGLE_DEG = 1.0  # rotation noise of a frame (solvers_1ac.py)
FRAME_LOG_SCALE = 0.02  # scale noise of a frame, log
OUTLIER_LOG_SCALE = 0.5  # an outlier's random frame: any rotation, scale exp(N(0, 0.5))
GENERATORS = ("2p1p", "1ac1p", "mixed")
FRAMES = ("affine", "similarity")


# ---- the frames of the matches -----------------------------------------------------------------


def patch_affine(
    R: np.ndarray, t: np.ndarray, xq: np.ndarray, xr: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """The local affine map ``∂x_r/∂x_q`` (2, 2) at the match ``(xq, xr)`` (rays ``(x, y, 1)``) of
    a surface patch with ``normal`` (query frame) through the point the match triangulates to
    under ``ref_from_query = (R, t)``: the Jacobian of the plane's homography ``R + t nᵀ / d``."""
    depths, *_ = np.linalg.lstsq(np.stack([R @ xq, -xr], axis=1), -t, rcond=None)
    X = depths[0] * xq
    H = R + np.outer(t, normal) / float(normal @ X)
    y = H @ xq
    return (H[:2, :2] - np.outer(y[:2] / y[2], H[2, :2])) / y[2]


def frame_noise(rng: np.random.Generator, A: np.ndarray) -> np.ndarray:
    """``A`` (n, 2, 2) rotated by N(0, 1°) and scaled by exp(N(0, 2 %)) each."""
    n = len(A)
    angle = np.radians(rng.normal(0.0, FRAME_ANGLE_DEG, n))
    scale = np.exp(rng.normal(0.0, FRAME_LOG_SCALE, n))
    return scale[:, None, None] * (rot2(angle) @ A)


def match_frames(rng: np.random.Generator, sc, model: str) -> np.ndarray:
    """(N, 2, 2) normalized local affine maps of every match of the scene, in the order of the
    estimator's flattened rows (pair after pair)."""
    cam = sc.query_camera
    out = []
    for pair, outlier in zip(sc.pairs, sc.is_outlier):
        R = pair.ref_pose.R @ sc.query_pose.R.T
        t = pair.ref_pose.t - R @ sc.query_pose.t
        xq = np.column_stack([(pair.query_points - cam.principal_point) / cam.focal, np.ones(len(pair))])
        rc = pair.ref_camera
        xr = np.column_stack([(pair.ref_points - rc.principal_point) / rc.focal, np.ones(len(pair))])
        A = np.empty((len(pair), 2, 2))
        for i in range(len(pair)):
            normal = rng.normal(size=3)
            normal -= 1.5 * np.linalg.norm(normal) * xq[i] / np.linalg.norm(xq[i])  # faces the query
            A[i] = patch_affine(R, t, xq[i], xr[i], normal / np.linalg.norm(normal))
        if model == "similarity":
            A = nearest_similarity(A)
        A = frame_noise(rng, A)
        k = int(outlier.sum())
        A[outlier] = np.exp(rng.normal(0.0, OUTLIER_LOG_SCALE, k))[:, None, None] * rot2(
            rng.uniform(-np.pi, np.pi, k)
        )
        out.append(A)
    return np.ascontiguousarray(np.concatenate(out))


# ---- the 1ac1p estimator -------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def relative_candidates_1ac(rows, A, prob, settings, out) -> int:
    """Stage 1 of 1ac1p: the planar relative pose of each drawn affine correspondence (rows (S,),
    frames A (N, 2, 2)), scored by MSAC on its own pair (every s-th match, as the 2-point stage
    of :func:`planarloc.robust.consensus_scale.planar_relative_candidates`), and per pair the
    ``top_k`` best distinct ones written to ``out``; returns how many."""
    S = rows.shape[0]
    xq, xr, offsets, f_query, f_ref = prob.xq, prob.xr, prob.offsets, prob.f_query, prob.f_ref
    thetas = np.zeros((S, 2))
    phis = np.zeros((S, 2))
    cost = np.full(2 * S, np.inf)
    samples = np.empty((S, 2), dtype=np.int64)
    top_k, threshold_sq = settings.top_k, settings.threshold_sq
    # Per pair, the top_k smallest costs so far: a candidate whose partial cost exceeds the last
    # cannot be kept, so its scoring stops early (as in the 2-point stage).
    bound = np.full((offsets.shape[0] - 1, top_k), np.inf)
    sol = np.empty(3)
    R = np.empty((3, 3))
    t = np.empty(3)
    E = np.empty((3, 3))
    for s in range(S):
        i = rows[s]
        samples[s, 0] = i
        samples[s, 1] = i
        if solve_planar_1ac(xq[i], xr[i], A[i], sol) == 0:
            out.counters[DEGENERATE] += 1
            continue
        thetas[s, 0], phis[s, 0] = sol[0], sol[1]
        planar_pose_into(sol[0], sol[1], R, t)
        for c in range(3):  # E = [t]x R
            E[0, c] = t[1] * R[2, c] - t[2] * R[1, c]
            E[1, c] = t[2] * R[0, c] - t[0] * R[2, c]
            E[2, c] = t[0] * R[1, c] - t[1] * R[0, c]
        p = prob.pair[i]
        n_p = offsets[p + 1] - offsets[p]
        acc = 0.0
        worst = bound[p, top_k - 1]
        for m in range(
            offsets[p], offsets[p + 1], max(1, (n_p + settings.max_scored - 1) // settings.max_scored)
        ):
            e = sampson_sq(E, xq[m], xr[m], f_query[0], f_query[1], f_ref[p, 0], f_ref[p, 1])
            acc += e if e < threshold_sq else threshold_sq
            if acc > worst:
                break
        if acc > worst:
            continue
        cost[2 * s] = acc
        q = top_k - 1  # insert acc into the pair's ascending bound
        while q > 0 and bound[p, q - 1] > acc:
            bound[p, q] = bound[p, q - 1]
            q -= 1
        bound[p, q] = acc
    found = _keep_distinct(cost, thetas, phis, samples, prob, top_k, out)
    for q in range(found):
        planar_pose_into(out.t[q, 1], out.R[q, 1, 0], out.R[q], out.t[q])
    return found


class Planar1ac1pEstimator(Planar2p1pEstimator):
    """2p1p's consensus search with 1ac samples for its relative poses (``generator="1ac1p"``) or
    half of them (``"mixed"``); ``frames`` (N, 2, 2) the matches' normalized local affine maps."""

    def __init__(self, problem, options: RansacOptions, frames: np.ndarray, generator: str) -> None:
        super().__init__(problem, options)
        self.frames = frames
        self.generator = generator
        self.sample_size = 2 if generator == "1ac1p" else 3

    def _generate_1ac(self, rng: np.random.Generator, n: int, stats) -> tuple[np.ndarray, np.ndarray]:
        p = self.p
        samples = np.empty((n, 2), dtype=np.int64)
        sample_pair = np.empty(n, dtype=np.int64)
        draw_pair_samples(
            rng.random((n, 4)), p.offsets, 2, 0, samples, sample_pair, np.empty(n, dtype=np.int64)
        )
        candidates = RelativeCandidates.empty(self.top_k * p.num_pairs, self.counters)
        rows = np.ascontiguousarray(samples[:, 0])
        c = relative_candidates_1ac(rows, self.frames, p.arrays, self._consensus, candidates)
        found = Hypotheses.empty(c * self.peaks, self.counters)
        m = hypotheses_2p1p_consensus(candidates.first(c), p.arrays, self._consensus, found)
        self._flush(stats)
        return found.first(m)

    def _generate_consensus(self, rng: np.random.Generator, n: int, stats) -> tuple[np.ndarray, np.ndarray]:
        if not self._any_eligible:
            return np.zeros((0, 3, 3)), np.zeros((0, 3))
        if self.generator == "1ac1p":
            return self._generate_1ac(rng, n, stats)
        R1, t1 = self._generate_1ac(rng, n - n // 2, stats)
        R2, t2 = super()._generate_consensus(rng, n // 2, stats)
        return np.concatenate([R1, R2]), np.concatenate([t1, t2])


@dataclass
class _Injection:
    """What the replaced estimator factory builds for the planar family: nothing (the library's
    2p1p) or a 1ac1p / mixed estimator on the current scene's frames."""

    frames: np.ndarray | None = None
    generator: str = "2p1p"


_INJECT = _Injection()
_LIBRARY_ESTIMATOR = absolute_pose._estimator


def _estimator(problem, options, family, gravity):
    if family == Method.P2P1 and _INJECT.frames is not None and gravity.levelled:
        return Planar1ac1pEstimator(problem, options, _INJECT.frames, _INJECT.generator)
    return _LIBRARY_ESTIMATOR(problem, options, family, gravity)


# ---- the run ----------------------------------------------------------------------------------------


def budget_options(budget: str, seed: int) -> RansacOptions:
    fixed = replace(rb.paper_options(rb.THRESHOLD_PX, seed), cross_check=False)
    return fixed if budget == "fixed" else replace(fixed, min_iterations=1, max_iterations=1000)


def run(args: argparse.Namespace) -> dict:
    matches = rb.PROTOCOLS["hard"][2]
    absolute_pose._estimator = _estimator
    methods = [("2p1p", None)] + [(g, f) for g in GENERATORS[1:] for f in args.frames]
    rows: dict = defaultdict(lambda: defaultdict(list))
    peer_cpu = 0.0
    scenes = 0
    for mi, m in enumerate(matches):
        for ri, outliers in enumerate(rb.OUTLIERS):
            for trial in range(args.trials):
                sc, ransac_seed = rb.trial_scene("hard", args.seed, mi, ri, trial)
                frames = {
                    f: match_frames(np.random.default_rng([args.seed, mi, ri, trial]), sc, f)
                    for f in args.frames
                }
                c0 = time.process_time()
                estimate_query_pose_poselib(
                    sc.query_camera,
                    sc.pairs,
                    iterations=rb.ITERATIONS,
                    threshold_px=rb.THRESHOLD_PX,
                    seed=ransac_seed,
                )
                peer_cpu += time.process_time() - c0
                scenes += 1
                for budget in args.budgets:
                    opts = budget_options(budget, ransac_seed)
                    # The order rotates from scene to scene: the method run right after PoseLib (or
                    # after another method) finds the caches in another state.
                    turn = scenes % len(methods)
                    for generator, frame in methods[turn:] + methods[:turn]:
                        _INJECT.frames = None if frame is None else frames[frame]
                        _INJECT.generator = generator
                        c0 = time.process_time()
                        est = absolute_pose.estimate_absolute_pose(sc.query_camera, sc.pairs, "2p1p", opts)
                        cpu = time.process_time() - c0
                        pose = est.pose
                        ok = broken = False
                        if pose is not None:
                            dc, dr = pose_errors(pose, sc.query_pose)
                            ok = dc < rb.MAX_CENTRE_ERROR_M and dr < rb.MAX_ROTATION_ERROR_DEG
                            broken = dc > 3.0 * est.position_std_m + 0.05
                        r = rows[(budget, generator if frame is None else f"{generator}/{frame}")]
                        r["cpu"].append(cpu)
                        r["ok"].append(ok)
                        r["success"].append(est.success)
                        r["broken"].append(broken)
                        r["iterations"].append(est.stats.iterations)
                        r["cell"].append((m, outliers))
    _INJECT.frames = None
    absolute_pose._estimator = _LIBRARY_ESTIMATOR
    return {"scenes": scenes, "peer_ms": 1e3 * peer_cpu / scenes, "rows": rows}


def report(result: dict) -> dict:
    peer = result["peer_ms"]
    print(f"{result['scenes']} hard-protocol scenes; PoseLib {peer:.3f} ms per scene")
    print(
        f"{'budget':8s} {'method':20s} {'success':>8s} {'20 m/60 %':>9s} {'broken':>7s} {'samples':>8s} "
        f"{'ms':>7s} {'/PoseLib':>8s}"
    )
    out = {}
    for (budget, name), r in result["rows"].items():
        hard = [o for o, cell in zip(r["ok"], r["cell"]) if cell == (20, 0.6)]
        row = {
            "success_pct": 100.0 * float(np.mean(r["ok"])),
            "success_20_60_pct": 100.0 * float(np.mean(hard)) if hard else float("nan"),
            "broken": int(np.sum(r["broken"])),
            "successes": int(np.sum(r["success"])),
            "samples": float(np.mean(r["iterations"])),
            "ms": 1e3 * float(np.mean(r["cpu"])),
        }
        row["ratio"] = row["ms"] / peer
        out[f"{budget} {name}"] = row
        print(
            f"{budget:8s} {name:20s} {row['success_pct']:7.1f}% {row['success_20_60_pct']:8.1f}% "
            f"{row['broken']:3d}/{row['successes']:<4d}{row['samples']:7.0f} {row['ms']:7.3f} "
            f"{row['ratio']:8.2f}"
        )
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", type=int, default=40, help="scenes per cell, 10 cells (default: %(default)s)")
    p.add_argument("--seed", type=int, default=70, help="base seed (default: %(default)s)")
    p.add_argument(
        "--budgets",
        nargs="+",
        choices=("fixed", "adaptive"),
        default=["fixed", "adaptive"],
        help="search budgets",
    )
    p.add_argument("--frames", nargs="+", choices=FRAMES, default=list(FRAMES), help="frame models of 1ac1p")
    p.add_argument("--json", type=Path, help="write the table here")
    args = p.parse_args(argv)
    if args.trials < 1:
        p.error("--trials must be >= 1")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    print("[method_1ac1p] warming up ...", file=sys.stderr)
    rb.warm_up()
    warm = parse_args(["--trials", "1", "--seed", "999"])
    warm.budgets, warm.frames = args.budgets, args.frames
    run(warm)  # every kernel of every variant loaded before anything is timed
    table = report(run(args))
    if args.json:
        args.json.write_text(json.dumps({"trials": args.trials, "seed": args.seed, "rows": table}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
