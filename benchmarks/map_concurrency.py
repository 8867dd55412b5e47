"""Concurrent `planarloc map build`s on one map file: never a damaged map, never lost images.

Each repetition starts two real `planarloc map build` processes on the same (new) map file of a
small generated world (12 map images, TUM layout), a few milliseconds apart. Every third
repetition additionally kills the first builder with SIGKILL at a random moment and then runs a
third build to completion (resume after a crash while another writer is active). After each
repetition the map must pass `planarloc.map.integrity.check_map`, hold all 12 images,
be marked complete, and every builder that was not killed must have exited 0.

    python benchmarks/map_concurrency.py                 # 30 repetitions
    python benchmarks/map_concurrency.py --reps 5 --json out/concurrency.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from planarloc.map.integrity import check_map
from planarloc.map.store import MapDatabase
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk

N_MAP = 12


def builder(dataset: Path, out: Path) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "planarloc.cli.main",
        "map",
        "build",
        str(dataset),
        "-f",
        "tum",
        "--out",
        str(out),
        "--max-features",
        "1000",
        "--vocabulary-size",
        "16",
    ]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(
            [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]
        ),
    }
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def one_repetition(dataset: Path, out: Path, rng: np.random.Generator, kill: bool) -> dict:
    t0 = time.perf_counter()
    first = builder(dataset, out)
    time.sleep(float(rng.uniform(0.0, 0.3)))
    second = builder(dataset, out)
    killed = False
    if kill:
        time.sleep(float(rng.uniform(2.0, 6.0)))
        if first.poll() is None:
            first.send_signal(signal.SIGKILL)
            killed = True
    procs = [first, second]
    outcomes = [(p.wait(timeout=600), p.stderr.read()) for p in procs]
    if killed:  # a third build resumes whatever the killed one left
        third = builder(dataset, out)
        outcomes.append((third.wait(timeout=600), third.stderr.read()))
    report = check_map(out)
    with MapDatabase.open(out) as db:
        num, complete = db.num_images(), db.is_complete
    expected_ok = [rc == 0 for i, (rc, _) in enumerate(outcomes) if not (killed and i == 0)]
    errors = [err.strip().splitlines()[-1] for rc, err in outcomes if rc != 0 and err.strip()]
    ok = report.ok and num == N_MAP and complete and all(expected_ok)
    return {
        "ok": ok,
        "killed": killed,
        "images": num,
        "complete": complete,
        "problems": report.problems,
        "exit_codes": [rc for rc, _ in outcomes],
        "errors": errors,
        "seconds": time.perf_counter() - t0,
        "waited": sum("being built by PID" in err for _, err in outcomes),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        world = generate(
            shrunk(get_preset("office"), scale=0.5, n_map=N_MAP, n_query=2), Path(tmp) / "w", seed=0
        )
        results = []
        for rep in range(args.reps):
            r = one_repetition(world / "map", Path(tmp) / f"map{rep}.db", rng, kill=rep % 3 == 2)
            results.append(r)
            print(
                f"rep {rep + 1:2d}/{args.reps}: {'ok ' if r['ok'] else 'BAD'} images {r['images']:2d} "
                f"complete {r['complete']!s:5} exit {r['exit_codes']} killed {r['killed']!s:5} "
                f"waited {r['waited']} {r['seconds']:.1f} s {r['problems'][:1]} {r['errors'][:1]}",
                file=sys.stderr,
                flush=True,
            )
    bad = [r for r in results if not r["ok"]]
    summary = {
        "repetitions": len(results),
        "ok": len(results) - len(bad),
        "bad": len(bad),
        "killed_runs": sum(r["killed"] for r in results),
        "runs_where_a_builder_waited": sum(r["waited"] > 0 for r in results),
    }
    print(json.dumps(summary))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"summary": summary, "repetitions": results}, indent=1))
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
