"""`planarloc warmup`: compile (or load from numba's on-disk cache) every kernel a query uses.

numba compiles a kernel on its first call and caches the machine code next to the module
(``__pycache__/*.nbi, *.nbc``). A fresh container without those files would pay the
compilation (tens of seconds) on its first query; running ``planarloc warmup`` once when the
image is built (e.g. a ``RUN planarloc warmup`` line after ``pip install``) writes the cache
into the image, so the first query only loads it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, progress_bar
from planarloc.cli.exit_codes import WARMUP_RESUMES
from planarloc.geometry.pose import Pose
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import Method, RansacOptions
from planarloc.synthetic.scenes import make_scene


def warm_up(update=None) -> dict[str, float]:
    """Run every estimator path once on small generated scenes; returns seconds per step.

    Steps: each method with ``structure="none"`` and ``"tracks"`` on a spread scene, 2p1p on
    a collinear scene (the degeneracy analysis: map covariance and cost profile), and the
    single-call solver APIs.
    """
    import planarloc.solvers as S

    rng = np.random.default_rng(0)
    spread = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.3, track_pool=1.5)
    line = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.2, collinear=True)
    opts = RansacOptions(max_iterations=20, min_iterations=20)
    steps = [(f"{m.value} {s}", lambda m=m, s=s: estimate_absolute_pose(
                 spread.query_camera, spread.pairs, m, RansacOptions(max_iterations=20, min_iterations=20,
                                                                      structure=s)))
             for m in Method for s in ("none", "tracks")]
    steps.append(("2p1p collinear", lambda: estimate_absolute_pose(line.query_camera, line.pairs, "2p1p", opts)))
    xq = np.array([[0.1, 0.2, 1.0], [-0.3, 0.1, 1.0], [0.2, -0.1, 1.0], [0.05, 0.3, 1.0], [-0.2, -0.2, 1.0],
                   [0.3, 0.25, 1.0], [-0.1, 0.05, 1.0], [0.15, -0.3, 1.0]])
    xr = xq + np.array([0.02, 0.0, 0.0])
    rel = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))  # unit baseline to a reference
    ref1, ref2 = Pose.identity(), Pose.from_center(np.eye(3), np.array([0.0, 0.0, 2.0]))
    steps.append(("solvers", lambda: (S.relpose_planar_2p(xq[:2], xr[:2]), S.relpose_5p_nister(xq[:5], xr[:5]),
                                      S.relpose_5p_stewenius(xq[:5], xr[:5]), S.relpose_8p(xq, xr),
                                      S.essentials_5p_nister(xq[:5], xr[:5]),
                                      S.essentials_5p_stewenius(xq[:5], xr[:5]), S.essential_8p(xq, xr),
                                      S.abspose_up2p(xq[:2], 5 * xq[:2]), S.abspose_2p2p(rel, rel, ref1, ref2),
                                      S.abspose_2p1p(rel, ref1, ref2, xq[0], xr[0]))))
    times = {}
    for i, (name, fn) in enumerate(steps):
        t0 = time.perf_counter()
        fn()
        times[name] = time.perf_counter() - t0
        if update is not None:
            update("warm-up", i + 1, len(steps))
    return times


def add_parser(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "warmup", "compile or load every numba kernel once (run at image build time)",
                """Compile every numba kernel a query uses (or load it from numba's on-disk cache) by running
                each estimator once on small generated scenes. The first run on a machine takes tens of
                seconds; later runs, and queries, only load the cache. In a Dockerfile, after pip install:
                RUN planarloc warmup""",
                ["planarloc warmup"], run, interrupted=WARMUP_RESUMES)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    with progress_bar() as update:
        times = warm_up(update)
    slowest = max(times, key=times.get)
    info(f"warm-up done in {time.perf_counter() - t0:.1f} s (slowest step: {slowest}, "
                  f"{times[slowest]:.1f} s)")
    return 0
