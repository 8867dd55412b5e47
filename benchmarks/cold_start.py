"""Cold start of a fresh container: `planarloc warmup` once, then the first query of a new process.

The tree of the current git commit is copied (``git archive``) into a temporary folder, so no
numba cache (``__pycache__/*.nbi, *.nbc``) exists; ``planarloc warmup`` is run there, and then
a *new* Python process imports planarloc from the copy, generates a scene and localizes one
query (5 references x 100 matches, ``structure="tracks"``). Printed: the warmup's wall and CPU
time, and the new process' import + scene time and first-query time (issue 10: ≤ 10 s).

Usage::

    python benchmarks/cold_start.py
    python benchmarks/cold_start.py --keep /tmp/cold    # keep the copy (and its cache)
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

FIRST_QUERY = """
import time
t0 = time.perf_counter()
import numpy as np
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions
from planarloc.synthetic.scenes import make_scene
sc = make_scene(np.random.default_rng(7), num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.4,
                track_pool=1.5)
t1 = time.perf_counter()
est = estimate_absolute_pose(sc.query_camera, sc.pairs, options=RansacOptions(structure="tracks"))
t2 = time.perf_counter()
print(f"{t1 - t0:.2f} {t2 - t1:.2f} {est.status}")
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", type=Path, help="copy the tree here and keep it (default: a temporary folder)")
    args = ap.parse_args(argv)
    root = args.keep or Path(tempfile.mkdtemp(prefix="planarloc-cold-"))
    if root.exists() and any(root.iterdir()):
        print(f"--keep {root}: folder exists and is not empty; choose a new one", file=sys.stderr)
        return 2
    root.mkdir(parents=True, exist_ok=True)
    try:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", "HEAD"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
        env = {**os.environ, "PYTHONPATH": str(root)}
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "planarloc.cli.main", "warmup"], cwd=root, env=env, check=True,
                       stdout=subprocess.DEVNULL)
        warm_wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        warm_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        cached = len(list(root.rglob("*.nbi")))
        t1 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", FIRST_QUERY], cwd=root, env=env, check=True,
                             capture_output=True, text=True).stdout.split()
        total = time.perf_counter() - t1
        setup_s, query_s, status = float(out[0]), float(out[1]), out[2]
        print(f"warmup (no numba cache): {warm_wall:.1f} s wall, {warm_cpu:.1f} s CPU, {cached} cached kernel indexes")
        print(f"fresh process: imports + scene {setup_s:.2f} s, first query {query_s:.2f} s ({status}); "
              f"process wall {total:.2f} s; load average {os.getloadavg()[0]:.2f}")
        return 0
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
