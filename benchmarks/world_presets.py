"""Generated indoor worlds: office, corridor, lifelong (``planarloc/synthetic/world``).

For each preset the world is rendered (map and query trajectories, TUM layout), the map is
built from the map trajectory (no tilt; for ``lifelong`` also with tilt) and every query
image is localized with 2p1p, structure ``none`` (the paper's 2D-2D constraints) and
``tracks``. A *confident-but-wrong* query is one reported as ``success`` whose pose is off by
more than 0.25 m or 10°: the failure mode that a localizer must not have.

Targets (PASS/FAIL lines; the exit code only reports crashes):
- office: tracks >= 90 % at 0.25 m/10°.
- corridor (straight, forward motion: degenerate for 2D-2D): structure none reports degenerate
  queries and returns no confident-but-wrong pose; tracks localizes >= 90 % of the queries that
  none reported as degenerate (within 0.25 m/10°).
- lifelong (lighting change, moved objects): tracks >= 90 % at 0.25 m/10° with and without tilt.

    python benchmarks/world_presets.py --json worlds.json
    python benchmarks/world_presets.py --presets corridor --work-dir /tmp/worlds   # keep the renders
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402
from _datasets import SUMMARY_HEADERS, WRONG_R, WRONG_T, confident_wrong, is_wrong, summary_cells  # noqa: E402

from planarloc.evaluation.queries import (  # noqa: E402
    THRESHOLDS,
    config_label,
    evaluate_configs,
    summarize,
    threshold_name,
)
from planarloc.features.extract import FeatureConfig  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import LocalizerConfig  # noqa: E402
from planarloc.map.builder import build_map  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402
from planarloc.synthetic.world.export import generate  # noqa: E402
from planarloc.synthetic.world.presets import preset_names  # noqa: E402

STRICT = threshold_name(*THRESHOLDS[0])
TARGET_SUCCESS = 90.0
STRUCTURES = ("none", "tracks")
DEFAULT_PRESETS = ("office", "corridor", "lifelong")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--presets",
        nargs="+",
        default=list(DEFAULT_PRESETS),
        choices=preset_names(),
        help="worlds to run (default: %(default)s; trust.py covers pitched and offplane)",
    )
    p.add_argument("--seed", type=int, default=0, help="world seed (default: %(default)s)")
    p.add_argument("--method", default="2p1p", help="solver (default: %(default)s)")
    p.add_argument(
        "--work-dir",
        type=Path,
        help="keep rendered worlds here and reuse them (default: a temporary folder); maps are rebuilt",
    )
    p.add_argument("--json", type=Path, help="write all summaries and per-query results here")
    return p.parse_args(argv)


def row(preset: str, tilt: bool, s: dict) -> list[str]:
    return [preset, "tilt" if tilt else "-", *summary_cells(s)]


HEADERS = ["world", "tilt", *SUMMARY_HEADERS]


def run_preset(preset: str, args: argparse.Namespace, work: Path, maps: Path) -> list[dict]:
    t0 = time.perf_counter()
    world = generate(
        preset,
        work / f"world-{preset}-seed{args.seed}",
        seed=args.seed,
        progress=lambda d, n: progress(f"render {preset}", d, n),
    )
    render_s = time.perf_counter() - t0
    map_images, queries = read_dataset(world / "map", "tum"), read_dataset(world / "query", "tum")
    runs = []
    for tilt in (False, True) if preset == "lifelong" else (False,):
        features = FeatureConfig(tilt=tilt)
        path = maps / f"{preset}-{features.name}.db"
        t0 = time.perf_counter()
        build_map(map_images, path, features, progress=progress)
        build_s = time.perf_counter() - t0
        configs = [LocalizerConfig(method=args.method, ransac=RansacOptions(structure=s)) for s in STRUCTURES]
        t0 = time.perf_counter()
        with MapDatabase.open(path) as db:
            results = evaluate_configs(
                db, configs, queries, lambda d, n: progress(f"localize {preset}", d, n)
            )
        eval_s = time.perf_counter() - t0
        summaries = [
            summarize(r, *config_label(c), preset=preset, seed=args.seed, tilt=tilt)
            for c, r in zip(configs, results)
        ]
        runs.append(
            {
                "preset": preset,
                "tilt": tilt,
                "map_images": len(map_images),
                "queries": len(queries),
                "render_seconds": render_s,
                "build_seconds": build_s,
                "evaluate_seconds": eval_s,
                "load_average": peer.load_average(),
                "summaries": summaries,
            }
        )
        peer.log(
            f"{preset}{' (tilt)' if tilt else ''}: build {build_s:.0f} s, localization {eval_s:.0f} s; "
            f"{peer.load_note()}"
        )
    return runs


def targets(runs: list[dict]) -> list[tuple[bool, str]]:
    by = {(r["preset"], r["tilt"]): {s["structure"]: s for s in r["summaries"]} for r in runs}
    out = []
    if ("office", False) in by:
        v = by[("office", False)]["tracks"]["success"][STRICT]
        out.append(
            (v >= TARGET_SUCCESS, f"office: tracks {v:.1f}% at {STRICT} (target >= {TARGET_SUCCESS:g}%)")
        )
    if ("corridor", False) in by:
        none, tracks = by[("corridor", False)]["none"], by[("corridor", False)]["tracks"]
        wrong = confident_wrong(none)
        degenerate = [q["name"] for q in none["per_query"] if q["status"] == "degenerate_scale"]
        out.append(
            (
                not wrong and len(degenerate) > 0,
                f"corridor: none reports {len(degenerate)}/{none['queries']} queries degenerate and "
                f"{len(wrong)} confident-but-wrong (> {WRONG_T:g} m or > {WRONG_R:g}°; target: > 0 "
                f"degenerate, 0 wrong){': ' + ', '.join(wrong[:5]) if wrong else ''}",
            )
        )
        solved = [
            q
            for q in tracks["per_query"]
            if q["name"] in set(degenerate) and q["success"] and not is_wrong(q)
        ]
        pct = 100.0 * len(solved) / max(len(degenerate), 1)
        out.append(
            (
                len(degenerate) > 0 and pct >= TARGET_SUCCESS,
                f"corridor: tracks localizes {len(solved)}/{len(degenerate)} of the queries none reported "
                f"degenerate within {WRONG_T:g} m/{WRONG_R:g}° ({pct:.0f}%, target >= {TARGET_SUCCESS:g}%); "
                f"tracks overall {tracks['success'][STRICT]:.1f}% at {STRICT}, "
                f"{len(confident_wrong(tracks))} confident-but-wrong",
            )
        )
    for tilt in (False, True):
        if ("lifelong", tilt) in by:
            v = by[("lifelong", tilt)]["tracks"]["success"][STRICT]
            out.append(
                (
                    v >= TARGET_SUCCESS,
                    f"lifelong {'with' if tilt else 'without'} tilt: tracks {v:.1f}% at "
                    f"{STRICT} (target >= {TARGET_SUCCESS:g}%)",
                )
            )
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    peer.print_header(
        f"# Generated worlds: {', '.join(args.presets)} (seed {args.seed}); method {args.method}, "
        f"structures {', '.join(STRUCTURES)}, VLAD top-5"
    )
    code = peer.code_version()
    tmp = tempfile.TemporaryDirectory(prefix="planarloc-worlds-")
    work = args.work_dir or Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    runs: list[dict] = []
    try:
        for preset in args.presets:
            runs += run_preset(preset, args, work, Path(tmp.name))
    finally:
        tmp.cleanup()
    rows = [row(r["preset"], r["tilt"], s) for r in runs for s in r["summaries"]]
    print()
    print(
        peer.markdown_table(
            HEADERS,
            rows,
            f"Generated worlds, {args.method}, map = map trajectory, queries = query trajectory",
        )
    )
    print(
        "; ".join(
            f"{r['preset']}{' tilt' if r['tilt'] else ''}: {r['map_images']} map / {r['queries']} queries, "
            f"build {r['build_seconds']:.0f} s"
            for r in runs
        )
    )
    verdicts = targets(runs)
    print()
    print("## Targets")
    for ok, text in verdicts:
        print(peer.verdict(ok, text))
    seconds = time.perf_counter() - t_start
    print(f"total {seconds:.0f} s; {peer.load_note('at end')}")
    peer.write_json(
        args.json,
        {
            "seed": args.seed,
            "method": args.method,
            "code": code,
            "runs": runs,
            "targets": [{"pass": ok, "target": t} for ok, t in verdicts],
            "seconds": seconds,
        },
    )
    return 0


progress = peer.Progress()

if __name__ == "__main__":
    sys.exit(main())
