"""`planarloc demo`: generate an indoor world, build its map, localize its query trajectory."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, progress_bar
from planarloc.cli.exit_codes import DEMO_RESUMES
from planarloc.cli.map_building import build_calibrated_map
from planarloc.cli.report import print_summary_table, write_json
from planarloc.cli.warmup_command import compile_ahead
from planarloc.compile import steps_for
from planarloc.evaluation.queries import config_label, evaluate_configs, summarize
from planarloc.features.extract import FeatureConfig
from planarloc.features.retrieval import DEFAULT_NUM_WORDS
from planarloc.io.datasets import read_dataset
from planarloc.io.output import atomic_output, check_output_dir
from planarloc.localize.localizer import LocalizerConfig
from planarloc.map.store import MapDatabase
from planarloc.robust.options import Method, RansacOptions
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import DEFAULT_PRESET, preset_names, preset_summaries


def add_parser(sub: argparse._SubParsersAction) -> None:
    presets = "\n\npresets:" + "".join(f"\n  {name:<9} {text}" for name, text in preset_summaries().items())
    p = add_command(
        sub,
        "demo",
        "map and localize a generated indoor world in one go (no data needed)",
        """Renders a small indoor world (textured rooms, furniture) seen by a wheeled robot along a map
        trajectory and a different query trajectory, builds the map from the map images and their poses, and
        localizes every query image with the paper's 2D-2D method (structure none) and with the
        structure-aware mode (tracks). Prints success rates at the paper's thresholds (stdout) and writes a
        trajectory plot.

        The generated world is in TUM RGB-D layout, so it also works with
          planarloc map build DIR/world/map --format tum --out map.db""",
        ["planarloc demo --preset corridor --out corridor-demo"],
        run,
        listing=presets,
        interrupted=DEMO_RESUMES,
    )
    p.add_argument(
        "--out", "-o", type=Path, default=Path("planarloc-demo"), help="output folder (default: %(default)s)"
    )
    p.add_argument(
        "--preset", default=DEFAULT_PRESET, choices=preset_names(), help="world preset (default: %(default)s)"
    )
    p.add_argument("--seed", type=int, default=0, help="world seed (default: %(default)s)")
    p.add_argument(
        "--method",
        "-m",
        default=Method(LocalizerConfig().method).value,
        choices=[m.value for m in Method],
        help="solver for both runs (default: %(default)s)",
    )
    p.add_argument("--tilt", action="store_true", help="tilt-augment the map features (paper Sec. III-B)")


def run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    out = args.out
    check_output_dir(out, "--out")  # before rendering anything
    features = FeatureConfig(tilt=args.tilt)
    configs = [
        LocalizerConfig(method=args.method, ransac=RansacOptions(structure=s)) for s in ("none", "tracks")
    ]
    compile_ahead(steps_for(configs))
    with progress_bar() as update:
        world = generate(
            args.preset, out / "world", seed=args.seed, progress=lambda d, n: update("render world", d, n)
        )
        map_images = read_dataset(world / "map", "tum")
        queries = read_dataset(world / "query", "tum")
        map_path = out / f"map-{features.name}.db"
        build_calibrated_map(map_images, map_path, features, DEFAULT_NUM_WORDS, update)
        with MapDatabase.open(map_path) as db:
            results = evaluate_configs(db, configs, queries, lambda d, n: update("localize", d, n))
    summaries = [
        summarize(r, *config_label(c), preset=args.preset, seed=args.seed, tilt=args.tilt)
        for c, r in zip(configs, results)
    ]
    print_summary_table(
        summaries,
        f"planarloc demo: {args.preset} world, {len(map_images)} map images, {len(queries)} queries",
    )
    write_json(out / "results.json", summaries)
    from planarloc.viz.trajectory import save_localization_plot

    centers = np.array([m.cam_from_world.center for m in map_images])
    for c, r in zip(configs, results):
        method, structure = config_label(c)
        path = out / f"trajectory-{method}-{structure}.png"
        with atomic_output(path) as tmp:
            save_localization_plot(tmp, centers, r, f"{args.preset}: {method}, structure={structure}")
        info(f"wrote {path}")
    info(f"done in {time.perf_counter() - t_start:.0f} s")
    return 0
