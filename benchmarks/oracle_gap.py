"""An estimator against its oracle on many scenes of one hard-protocol cell, with the failure diagnosis.

``--method 2p1p`` (default, the paper's method without the cross-check) or ``--method auto``
(the library's default estimator, default options but for the fixed 100 iterations and the 2D-2D
constraints of the protocol); the oracle is the same estimator fed only the true inliers.

The gap between 2p1p and ``2p1p-oracle`` (2p1p fed only the true inliers) at 20 matches per
pair and 60 % outliers moves by several points between sets of a few hundred scenes, so it is
measured here on thousands (``--scenes`` per seed, several ``--seeds``). Scenes are those of
``robustness.py --protocol hard`` (3 references, 1.5 px noise, 100 fixed iterations, success
0.1 m / 1°, the same ``RansacOptions``) but drawn from ``SeedSequence([seed, 777, k])``, a
stream the robustness benchmark does not use.

Every scene where the oracle succeeds and 2p1p does not is classified:

* ``gate``: 2p1p's pose is within 0.1 m / 1° but the verification refused it;
* ``search``: the truth, refined like our answer (:class:`final_refinement.FinalRefiner` from the true
  pose), has a lower MSAC cost than our answer: better sampling or local optimisation could
  have found it;
* ``objective``: our answer has the lower cost: no search fixes it, only another objective.

Usage::

    python benchmarks/oracle_gap.py --matches 20 --outliers 0.6 --scenes 600 --seeds 1 2 3 4 5
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _trial_runner import run_trials  # noqa: E402
from robustness import ITERATIONS, MAX_CENTRE_ERROR_M, MAX_ROTATION_ERROR_DEG, THRESHOLD_PX, inlier_pairs  # noqa: E402

from planarloc.geometry.pose import pose_errors  # noqa: E402
from planarloc.robust.absolute_pose import estimate_absolute_pose  # noqa: E402
from planarloc.robust.estimators import Planar2p1pEstimator  # noqa: E402
from planarloc.robust.final_refinement import FinalRefiner  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402
from planarloc.robust.problem import build_problem  # noqa: E402
from planarloc.synthetic.scenes import make_scene  # noqa: E402


def run_scene(task: tuple[int, int, int, float, bool, str]) -> dict:
    seed, k, matches, outliers, with_2p2p, method = task
    ss = np.random.SeedSequence([seed, 777, k])
    sc = make_scene(
        np.random.default_rng(ss), num_refs=3, matches_per_pair=matches, noise_px=1.5, outlier_ratio=outliers
    )
    opts = RansacOptions(
        max_iterations=ITERATIONS,
        min_iterations=ITERATIONS,
        threshold_px=THRESHOLD_PX,
        seed=int(ss.generate_state(1)[0]),
        structure="none",
        cross_check=method != "2p1p",
    )

    def judged(est) -> tuple[bool, bool, object]:
        pose = est.pose if est.success else est.unreliable_pose
        if pose is None:
            return False, False, None
        dc, dr = pose_errors(pose, sc.query_pose)
        good = dc < MAX_CENTRE_ERROR_M and dr < MAX_ROTATION_ERROR_DEG
        return bool(est.success and good), bool(good), pose

    est = estimate_absolute_pose(sc.query_camera, sc.pairs, method, opts)
    ok, good, pose = judged(est)
    oracle_ok = judged(estimate_absolute_pose(sc.query_camera, inlier_pairs(sc), method, opts))[0]
    r = {"ok": ok, "oracle": oracle_ok}
    if with_2p2p:
        r["2p2p"] = judged(estimate_absolute_pose(sc.query_camera, sc.pairs, "2p2p", opts))[0]
    if oracle_ok and not ok:
        if good:
            r["class"] = "gate"
        elif pose is None:
            r["class"] = f"no pose ({est.status})"
        else:
            scorer = Planar2p1pEstimator(build_problem(sc.query_camera, sc.pairs), opts)
            truth = FinalRefiner(scorer, opts)(sc.query_pose.R, sc.query_pose.t).score
            ours = float(scorer.score(pose.R[None], pose.t[None])[0][0])
            r["class"] = "search" if ours > truth else "objective"
    return r


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="example: python benchmarks/oracle_gap.py --matches 20 --outliers 0.6 "
        "--scenes 600 --seeds 1 2 3 4 5",
    )
    ap.add_argument("--matches", type=int, default=20, help="matches per pair (default 20)")
    ap.add_argument("--outliers", type=float, default=0.6, help="outlier ratio (default 0.6)")
    ap.add_argument("--scenes", type=int, default=600, help="scenes per seed (default 600)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="scene seeds (default 1-5)")
    ap.add_argument(
        "--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes (default 2)"
    )
    ap.add_argument("--with-2p2p", action="store_true", help="also run 2p2p on every scene")
    ap.add_argument(
        "--method",
        choices=["2p1p", "auto"],
        default="2p1p",
        help="2p1p (the paper's, no cross-check; default) or auto (the library's default)",
    )
    a = ap.parse_args()
    if a.matches < 2 or a.scenes < 1 or not 0.0 <= a.outliers < 1.0:
        ap.error(
            f"need --matches >= 2, --scenes >= 1, 0 <= --outliers < 1; got {a.matches}, {a.scenes}, "
            f"{a.outliers}"
        )
    tasks = [(s, k, a.matches, a.outliers, a.with_2p2p, a.method) for s in a.seeds for k in range(a.scenes)]

    def warm_up() -> None:
        sc = make_scene(
            np.random.default_rng(0), num_refs=3, matches_per_pair=20, noise_px=1.5, outlier_ratio=0.2
        )
        for method in ("2p1p", "2p2p", a.method):
            estimate_absolute_pose(
                sc.query_camera,
                sc.pairs,
                method,
                RansacOptions(max_iterations=20, min_iterations=20, structure="none"),
            )

    res = run_trials("oracle_gap", tasks, run_scene, a.jobs, warm_up)
    n = len(res)
    rate = {
        m: 100.0 * sum(r[m] for r in res) / n for m in ("ok", "oracle") + (("2p2p",) if a.with_2p2p else ())
    }
    print(
        f"{a.matches} matches/pair, {100 * a.outliers:.0f} % outliers, {n} scenes (seeds {a.seeds}): "
        f"{a.method} {rate['ok']:.1f} %, oracle {rate['oracle']:.1f} %, gap "
        f"{rate['oracle'] - rate['ok']:.1f} points" + (f", 2p2p {rate['2p2p']:.1f} %" if a.with_2p2p else "")
    )
    classes = Counter(r["class"] for r in res if "class" in r)
    print(
        f"oracle succeeds, {a.method} fails: {sum(classes.values())} ({dict(classes)}); "
        f"{a.method} succeeds, oracle fails: {sum(1 for r in res if r['ok'] and not r['oracle'])}"
    )


if __name__ == "__main__":
    main()
