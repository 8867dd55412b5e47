"""`planarloc evaluate`: map = every N-th frame of a dataset, queries = the rest; success rates."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from planarloc.cli.map_command import parse_dataset_options
from planarloc.cli.exit_codes import EXIT_OK, EXIT_PARTIAL
from planarloc.cli.options import (add_dataset_args, add_feature_args, add_localizer_args, check_vocabulary_size,
                                   feature_config, localizer_config)
from planarloc.cli.output_paths import atomic_output, check_output_file, dataset_files, input_files
from planarloc.cli.progress import console, notify, progress_bar
from planarloc.cli.report import print_summary_table, write_json
from planarloc.io.datasets import read_dataset
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.pipeline.evaluation import config_label, default_map_path, evaluate_queries, split_map_queries, summarize
from planarloc.pipeline.localizer import Localizer
from planarloc.pipeline.map_builder import build_map, check_map_settings


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="evaluate localization on a posed sequence (map = every N-th frame, queries = the rest)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Builds a map from the frames with index %% N == 0 (cached, or --map), localizes every other "
                    "frame and compares with its ground truth. Success thresholds are the paper's: "
                    "0.25 m/10°, 0.5 m/10°, 1.0 m/20°. A failed query counts as a failure.\n\n"
                    "example:\n  planarloc evaluate data/kitti_seq2 --format kitti --map-every 2 "
                    "--structure tracks --json kitti.json --plot kitti.png")
    add_dataset_args(p)
    p.add_argument("--map-every", type=int, required=True, help="frames with index %% N == 0 form the map")
    p.add_argument("--map", type=Path, help="map file to build/reuse (default: a cache file in the temp folder)")
    p.add_argument("--json", type=Path, help="write the summary and per-query results here")
    p.add_argument("--plot", type=Path, help="write the trajectory plot (paper Fig. 8) here")
    p.add_argument("--dataset-option", action="append", metavar="KEY=VALUE", help="importer option (repeatable)")
    add_feature_args(p)
    add_localizer_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Every option and output is checked before the first image is read.
    if args.map_every < 2:
        raise ValueError(f"--map-every must be >= 2 (otherwise there are no queries), got {args.map_every}")
    features = feature_config(args)
    num_words = check_vocabulary_size(args.vocabulary_size)
    config = localizer_config(args)
    dataset_options = parse_dataset_options(args.dataset_option)
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    root = Path(args.dataset)
    outputs = {"--map": args.map, "--json": args.json, "--plot": args.plot}
    _check_distinct(outputs)
    inputs = input_files([*dataset_files(root), args.pairs, root])
    for option in ("--json", "--plot"):
        check_output_file(outputs[option], option, input_files(inputs, with_map_sidecars=[args.map]))
    check_output_file(args.map, "--map", inputs)
    if args.map is not None:
        check_map_settings(args.map, features, num_words)
    images = read_dataset(args.dataset, args.format, **dataset_options)
    map_images, queries = split_map_queries(images, args.map_every)
    image_paths = [im.path for im in images]
    for option, path in outputs.items():
        check_output_file(path, option, image_paths)
    map_path = args.map or default_map_path(Path(args.dataset), args.map_every, features.name, map_images,
                                            settings=f"words={num_words}|{features}")
    console.print(f"map: {len(map_images)} frames -> {map_path}; queries: {len(queries)} frames")
    with progress_bar() as update:
        build_map(map_images, map_path, features, num_words=num_words, progress=update,
                  notify=notify)
        loc = Localizer(map_path, config)
        results = evaluate_queries(loc, queries, lambda d, n: update("localize", d, n), pairs)
    method, structure = config_label(config)
    summary = summarize(results, method, structure, dataset=str(args.dataset), map_every=args.map_every,
                        top_n=config.top_n, tilt=features.tilt)
    print_summary_table([summary], f"{Path(args.dataset).name}, map every {args.map_every}")
    write_json(args.json, summary)
    if args.plot:
        from planarloc.viz.trajectory import save_localization_plot

        centers = np.array([m.cam_from_world.center for m in map_images])
        with atomic_output(args.plot) as tmp:
            save_localization_plot(tmp, centers, results, f"{Path(args.dataset).name}: {method}, {structure}")
        console.print(f"wrote {args.plot}")
    errors = [r for r in results if r.status == "error"]
    if errors:
        console.print(f"[yellow]{len(errors)} of {len(results)} queries could not be processed[/] "
                      f"(e.g. {errors[0].reason}); they count as failed")
        return EXIT_PARTIAL
    return EXIT_OK


def _check_distinct(outputs: dict[str, Path | None]) -> None:
    seen: dict[str, str] = {}
    for option, path in outputs.items():
        if path is None:
            continue
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{option} {path}: the same path as {seen[key]}; give each output its own path")
        seen[key] = option
