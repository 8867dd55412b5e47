"""`planarloc evaluate`: map = every N-th frame of a dataset, queries = the rest; success rates."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from planarloc.cli.map_command import parse_dataset_options
from planarloc.cli.options import add_dataset_args, add_feature_args, add_localizer_args, feature_config, localizer_config
from planarloc.cli.progress import console, progress_bar
from planarloc.cli.report import print_summary_table, write_json
from planarloc.cli.sequence_cli import add_sequence_args, check_sequential_args, evaluate_sequential
from planarloc.io.datasets import read_dataset
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.pipeline.evaluation import config_label, default_map_path, evaluate_queries, split_map_queries, summarize
from planarloc.pipeline.localizer import Localizer
from planarloc.pipeline.map_builder import build_map


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="evaluate localization on a posed sequence (map = every N-th frame, queries = the rest)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Builds a map from the frames with index %% N == 0 (cached, or --map), localizes every other "
                    "frame and compares with its ground truth. Success thresholds are the paper's: "
                    "0.25 m/10°, 0.5 m/10°, 1.0 m/20°. A failed query counts as a failure.\n\n"
                    "example:\n  planarloc evaluate data/kitti_seq2 --format kitti --map-every 2 "
                    "--structure tracks --json kitti.json --plot kitti.png\n"
                    "  planarloc evaluate data/kitti_seq2 --format kitti --map-every 4 --structure tracks --sequential "
                    "--kidnap-at 10 --json seq.json   # the queries as one stream")
    add_dataset_args(p)
    p.add_argument("--map-every", type=int, required=True, help="frames with index %% N == 0 form the map")
    p.add_argument("--map", type=Path, help="map file to build/reuse (default: a cache file in the temp folder)")
    p.add_argument("--json", type=Path, help="write the summary and per-query results here")
    p.add_argument("--plot", type=Path, help="write the trajectory plot (paper Fig. 8) here")
    p.add_argument("--dataset-option", action="append", metavar="KEY=VALUE", help="importer option (repeatable)")
    add_feature_args(p)
    add_localizer_args(p)
    add_sequence_args(p, evaluate=True)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_sequential_args(args)
    images = read_dataset(args.dataset, args.format, **parse_dataset_options(args.dataset_option))
    map_images, queries = split_map_queries(images, args.map_every)
    features = feature_config(args)
    map_path = args.map or default_map_path(Path(args.dataset), args.map_every, features.name)
    config = localizer_config(args)
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    console.print(f"map: {len(map_images)} frames -> {map_path}; queries: {len(queries)} frames")
    with progress_bar() as update:
        build_map(map_images, map_path, features, num_words=args.vocabulary_size, progress=update)
        if not args.sequential:
            loc = Localizer(map_path, config)
            results = evaluate_queries(loc, queries, lambda d, n: update("localize", d, n), pairs)
    if args.sequential:
        return evaluate_sequential(args, map_path, queries, config)
    method, structure = config_label(config)
    summary = summarize(results, method, structure, dataset=str(args.dataset), map_every=args.map_every,
                        top_n=config.top_n, tilt=features.tilt)
    print_summary_table([summary], f"{Path(args.dataset).name}, map every {args.map_every}")
    write_json(args.json, summary)
    if args.plot:
        from planarloc.viz.trajectory import save_localization_plot

        centers = np.array([m.cam_from_world.center for m in map_images])
        save_localization_plot(args.plot, centers, results, f"{Path(args.dataset).name}: {method}, {structure}")
        console.print(f"wrote {args.plot}")
    return 0
