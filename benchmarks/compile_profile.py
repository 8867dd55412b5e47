"""Where the first use's numba compile time goes (issue 20): CPU per kernel and per signature.

Runs one target in a new process with an empty numba cache (``NUMBA_CACHE_DIR`` pointed at a new
temporary folder) and numba's compile events recorded (``numba:compile``, through
:class:`planarloc.compile.CompileRecorder`): each planarloc kernel's signatures and the
CPU seconds of each one's compilation, without the planarloc kernels compiled on the way.
Compiling ahead (the parallel compile workers of the commands) is switched off in that process
(:func:`planarloc.compile.compile_lazily`), so that every kernel compiles lazily where its events
are seen — the CPU a cold first use needs.

Targets:
  localize  ``planarloc localize`` of one KITTI frame against a map of every 4th frame (built
            first, in another process: no kernels involved)
  demo      ``planarloc demo`` (render, map build, both structure modes)
  fuse      the price of fewer compiled calls (issue 31): a new kernel whose only work is to call
            one compiled kernel (the final refinement, ``refine_until_stable``) twice, compiled
            after that kernel is in the cache (numba links the callee's code into the caller and
            optimises it again): what fusing Python-level stages into one kernel adds to a cold start
  ahead:N   compiling ahead as a cold ``planarloc localize`` does (the kernels of its warm-up step,
            ``auto tracks``) on N worker processes: wall, CPU of the workers, and how busy they
            were; ``ahead:1 ahead:2`` shows what a second core buys and what the per-process
            compilation of numba's own functions costs
  STEP      a warm-up step of ``planarloc warmup`` by name, e.g. ``"auto tracks"``

    python benchmarks/compile_profile.py localize demo
    python benchmarks/compile_profile.py localize --opt 2 --top 15 --json prof.json
    python benchmarks/compile_profile.py fuse ahead:1 ahead:2
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
KITTI = REPO.parent / "shared" / "data" / "kitti_seq2"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("targets", nargs="*", help="localize, demo, fuse, ahead:N or a warm-up step name")
    p.add_argument(
        "--kitti",
        type=Path,
        default=KITTI,
        help="KITTI sequence of the localize target (default: %(default)s)",
    )
    p.add_argument(
        "--opt",
        type=int,
        choices=(0, 1, 2, 3),
        help="NUMBA_OPT of the profiled process (default: numba's)",
    )
    p.add_argument("--top", type=int, default=25, help="kernels listed per target (default: %(default)s)")
    p.add_argument("--json", type=Path, help="write the measurements here")
    p.add_argument("--child", nargs=3, metavar=("TARGET", "WORK", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for target in args.targets:
        jobs = target.partition(":")[2] if target.startswith("ahead:") else "1"
        if not (jobs.isdigit() and int(jobs) >= 1):
            p.error(f"target {target!r}: ahead:N takes a number of worker processes N >= 1, e.g. ahead:2")
    return args


def _child(target: str, work: Path, out: Path) -> int:
    """The profiled process: run ``target`` with the compile events recorded."""
    from planarloc.cli import main as cli
    from planarloc.compile import CompileRecorder, compile_lazily, run_steps

    extra: dict = {}
    t0, c0 = time.perf_counter(), time.process_time()
    with compile_lazily(), CompileRecorder() as rec:  # lazy compilation, in this process
        if target == "localize":
            frame = sorted((work / "kitti" / "image_l").glob("*.png"))[1]
            code = cli.main(
                ["localize", "--map", str(work / "map.db"), str(frame), "--out", str(work / "q.txt")]
            )
        elif target == "demo":
            code = cli.main(["demo", "--out", str(work / "demo")])
        elif target == "fuse":
            extra = _fuse_cost()
            code = 0
        elif target.startswith("ahead:"):
            extra = _ahead_cost(int(target.partition(":")[2]))
            code = 0
        else:
            run_steps([target])
            code = 0
    out.write_text(
        json.dumps(
            {
                "kernels": rec.kernels,
                "overloads": rec.overloads,
                "wall_s": time.perf_counter() - t0,
                "cpu_s": time.process_time() - c0,
                "exit_code": code,
                **extra,
            }
        )
    )
    return int(code)


def _fuse_cost() -> dict:
    """Compile CPU of ``refine_until_stable`` on a small problem, then of a new kernel that calls
    it twice (``rounds`` a run-time value: a literal would compile another specialisation)."""
    import numpy as np
    from numba import njit

    from planarloc.robust.estimators import Planar2p1pEstimator
    from planarloc.robust.final_refinement import refine_until_stable
    from planarloc.robust.options import RansacOptions
    from planarloc.robust.problem import build_problem
    from planarloc.synthetic.scenes import make_scene

    sc = make_scene(
        np.random.default_rng(0), num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.0
    )
    problem = build_problem(sc.query_camera, sc.pairs)
    settings = Planar2p1pEstimator(problem, RansacOptions()).refine_settings(6)
    R, t, rounds = sc.query_pose.R.copy(), sc.query_pose.t.copy(), 4
    c0 = time.process_time()
    first = refine_until_stable(R, t, problem.arrays, settings, rounds)
    callee_s = time.process_time() - c0

    @njit
    def twice(R, t, prob, settings, rounds):
        return (
            refine_until_stable(R, t, prob, settings, rounds).score
            + refine_until_stable(R, t, prob, settings, rounds).score
        )

    c0 = time.process_time()
    fused = twice(R, t, problem.arrays, settings, rounds)
    caller_s = time.process_time() - c0
    if not np.isclose(fused, 2.0 * first.score):
        raise RuntimeError(f"the fused call disagrees: {fused} != 2 x {first.score}")
    return {"fuse": {"callee_compile_cpu_s": callee_s, "caller_compile_cpu_s": caller_s}}


def _ahead_cost(jobs: int) -> dict:
    """Compile the kernels of the ``auto tracks`` step as a cold localize does, on ``jobs``
    worker processes (the compile report times each task and each worker)."""
    from planarloc.compile import compile_kernels, load_manifest
    from planarloc.compile.cache import missing_kernels
    from planarloc.compile.schedule import estimated_seconds

    manifest = load_manifest()
    keys = missing_kernels(manifest.for_steps(["auto tracks"]), manifest)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = compile_kernels(keys, manifest, jobs)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {
        "ahead": {
            "jobs": jobs,
            "kernels": len(keys),
            "compiled": done.compiled,
            "failed": sorted(done.failed),
            "wall_s": done.seconds,
            "workers_cpu_s": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime,
            "busy_s": sorted(done.busy_seconds, reverse=True),
            "longest": sorted(done.task_seconds.items(), key=lambda kv: -kv[1])[:3],
            "estimated_s": estimated_seconds(keys, manifest, jobs),
        }
    }


def profile(target: str, args: argparse.Namespace, work: Path) -> dict:
    """Run ``target`` in a new process with an empty numba cache; its compile record."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_OPT"}
    env["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="cache-", dir=work)
    if args.opt is not None:
        env["NUMBA_OPT"] = str(args.opt)
    out = work / f"profile-{len(list(work.glob('profile-*')))}.json"
    peer.log(f"{target}: profiling (NUMBA_OPT={env.get('NUMBA_OPT', 'default')}, {peer.load_note().strip()})")
    subprocess.run(
        [sys.executable, __file__, "--child", target, str(work), str(out)],
        env=env,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return json.loads(out.read_text())


def report(target: str, rec: dict, top: int) -> None:
    if "fuse" in rec:
        f = rec["fuse"]
        callee, caller = f["callee_compile_cpu_s"], f["caller_compile_cpu_s"]
        print(
            f"{target}: refine_until_stable and its callees compile in {callee:.1f} s of CPU on an empty "
            f"cache; a new kernel that only calls it twice then takes {caller:.1f} s more "
            f"({caller / callee:.0%} of the callee's own)\n"
        )
        return
    if "ahead" in rec:
        a = rec["ahead"]
        print(
            f"{target}: {a['compiled']} of {a['kernels']} kernels compiled ahead on {a['jobs']} worker(s) in "
            f"{a['wall_s']:.1f} s wall, {a['workers_cpu_s']:.1f} s of the workers' CPU; each worker busy "
            + " / ".join(f"{b:.1f}" for b in a["busy_s"])
            + f" s; the notice's estimate {a['estimated_s']:.1f} s; longest single tasks "
            "(a bound on the wall with more cores): "
            + ", ".join(f"{k.partition(':')[2]} {v:.1f} s" for k, v in a["longest"])
            + (f"; failed: {a['failed']}" if a["failed"] else "")
            + "\n"
        )
        return
    kernels = rec["kernels"]
    total = sum(s for sigs in kernels.values() for s in sigs.values())
    nsig = sum(len(sigs) for sigs in kernels.values())
    rows = []
    for k, sigs in sorted(kernels.items(), key=lambda kv: -sum(kv[1].values()))[:top]:
        times = sorted(sigs.values(), reverse=True)
        rows.append(
            [
                k.removeprefix("planarloc."),
                len(sigs),
                f"{sum(times):.2f}",
                " + ".join(f"{t:.2f}" for t in times) if len(times) > 1 else "",
            ]
        )
    print(
        peer.markdown_table(
            ["kernel", "signatures", "compile CPU (s)", "per signature (s)"],
            rows,
            f"{target}: {len(kernels)} kernels, {nsig} signatures, {total:.1f} s of compile CPU "
            f"(process: {rec['cpu_s']:.1f} s CPU, {rec['wall_s']:.1f} s wall)",
        )
    )
    by_layer: dict[str, float] = defaultdict(float)
    for k, sigs in kernels.items():
        by_layer[k.split(".")[1]] += sum(sigs.values())
    print(
        "by layer: "
        + ", ".join(f"{layer} {s:.1f} s" for layer, s in sorted(by_layer.items(), key=lambda x: -x[1]))
    )
    ov = sorted(rec["overloads"].items(), key=lambda kv: -kv[1])
    print(
        f"numba's own functions compiled for them: {sum(rec['overloads'].values()):.1f} s in all; largest: "
        + ", ".join(f"{k.partition(':')[2]} ({k.partition(':')[0]}) {s:.1f} s" for k, s in ov[:6])
    )
    multi = {k: len(s) for k, s in kernels.items() if len(s) > 1}
    print(f"kernels with more than one signature: {multi or 'none'}\n")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        return _child(args.child[0], Path(args.child[1]), Path(args.child[2]))
    if not args.targets:
        print("give at least one target: localize, demo or a warm-up step name", file=sys.stderr)
        return 2
    peer.print_header("# numba compile CPU of a cold first use, per kernel and signature")
    results = {}
    with tempfile.TemporaryDirectory(prefix="planarloc-compile-") as tmp:
        work = Path(tmp)
        if "localize" in args.targets:
            if not (args.kitti / "image_l").is_dir():
                print(f"--kitti {args.kitti}: not a KITTI sequence (image_l/ missing)", file=sys.stderr)
                return 2
            (work / "kitti").symlink_to(args.kitti.resolve())
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "planarloc.cli.main",
                    "map",
                    "build",
                    str(args.kitti),
                    "-f",
                    "kitti",
                    "--every",
                    "4",
                    "--out",
                    str(work / "map.db"),
                ],
                check=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        for target in args.targets:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            rec = profile(target, args, work)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            rec["child_cpu_s"] = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
            rec["load_average_end"] = peer.load_average()
            results[target] = rec
            report(target, rec, args.top)
    print(peer.load_note())
    peer.write_json(args.json, {"opt": args.opt, "targets": results, "code": peer.code_version()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
