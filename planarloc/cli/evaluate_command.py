"""`planarloc evaluate`: map = every N-th frame of a dataset, queries = the rest, or map = some
sessions, queries = another (cross-session); success rates."""

from __future__ import annotations

import argparse
import os
from contextlib import closing
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import note, progress_bar
from planarloc.cli.cross_session import add_cross_session_args, read_map_and_queries
from planarloc.cli.exit_codes import EVALUATE_RESUMES
from planarloc.cli.map_building import build_calibrated_map, left_out_exit
from planarloc.cli.options import (
    add_dataset_args,
    add_feature_args,
    add_gravity_args,
    add_localizer_args,
    add_ray_arg,
    check_vocabulary_size,
    feature_config,
    localizer_config_of,
)
from planarloc.cli.report import partial_exit, print_summary_table, write_json, write_trajectory_plot
from planarloc.cli.result_outputs import EstimateOutputs, add_output_args, write_evaluation_tum
from planarloc.cli.sequence_cli import add_sequence_args, check_sequential_args, evaluate_sequential
from planarloc.cli.warmup_command import compile_ahead
from planarloc.compile import steps_for
from planarloc.distributed.ray_backend import ray_session
from planarloc.evaluation.queries import config_label, evaluate_queries, gravity_from_truth, summarize
from planarloc.features.extract import FeatureConfig
from planarloc.io.gravity_file import read_gravity_file
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.io.output import check_output_file, dataset_files, input_files
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.map.builder import check_map_settings
from planarloc.map.gravity import map_gravity
from planarloc.map.store import MapDatabase


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "evaluate",
        "evaluate localization on posed data (map = every N-th frame, or cross-session --queries)",
        """Builds a map from the frames with index % N == 0 (cached, or --map), localizes every other frame
        and compares with its ground truth. Success thresholds are the paper's: 0.25 m/10°, 0.5 m/10°, 1.0
        m/20°. A failed query counts as a failure. The table goes to stdout. Map images that cannot go into
        the map (unreadable, truncated, of another size than their camera) are left out and listed, as by
        `map build`, and the exit code is 3.

        Cross-session (map on Monday, localize on Friday; the paper's OpenLORIS protocol): give one or more
        map datasets and --queries QUERY_DATASET instead of --map-every. The JSON lists, per query, the map
        images it used (references).""",
        [
            "planarloc evaluate data/kitti_seq2 --format kitti --map-every 2 --structure tracks --json "
            "kitti.json --plot kitti.png",
            "planarloc evaluate worlds/office/map -f tum --map-every 3 --gravity-from-truth",
            "planarloc evaluate home1 home3 -f openloris --queries home2 --json home2.json --tum home2-tum",
            "planarloc evaluate monday/ -f tum --queries friday.bag --queries-format rosbag --queries-option "
            "pose_topic=/pose --plot-matches matches/",
            "planarloc evaluate data/kitti_seq2 --format kitti --map-every 4 --structure tracks --sequential "
            "--kidnap-at 10 --json seq.json   # the queries as one stream",
        ],
        run,
        interrupted=EVALUATE_RESUMES,
    )
    add_dataset_args(p, many=True)
    add_cross_session_args(p)
    p.add_argument(
        "--map", type=Path, help="map file to build/reuse (default: a cache file in the temp folder)"
    )
    p.add_argument("--json", type=Path, help="write the summary and per-query results here")
    p.add_argument(
        "--plot",
        type=Path,
        help="write the trajectory plot (paper Fig. 8; top view in the plane "
        "perpendicular to the map's gravity) here",
    )
    p.add_argument(
        "--dataset-option",
        action="append",
        metavar="KEY=VALUE",
        help="importer option (repeatable); up=AXIS gives the world's up direction, e.g. up=z",
    )
    add_gravity_args(
        p,
        "--gravity-from-truth",
        action="store_true",
        help="simulate an IMU: give each query its true gravity (ground-truth rotation x the world's "
        "down direction: the format's, up=..., or the map's estimate; see `map info`)",
    )
    add_feature_args(p)
    add_localizer_args(p)
    add_output_args(
        p,
        "write DIR/estimate.txt and DIR/groundtruth.txt (TUM, camera-to-world, localized queries) "
        "for `evo_ape tum DIR/groundtruth.txt DIR/estimate.txt`, and add evo's APE/RPE to the JSON",
    )
    add_ray_arg(p)
    add_sequence_args(p, evaluate=True)


def run(args: argparse.Namespace) -> int:
    # Every option and output is checked before the first image is read.
    _check_options(args)
    features = feature_config(args)
    num_words = check_vocabulary_size(args.vocabulary_size)
    config = localizer_config_of(args)
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    gravity = read_gravity_file(args.gravity_file) if args.gravity_file else None
    outputs = {"--map": args.map, "--json": args.json, "--plot": args.plot}
    _check_outputs(args, outputs)
    if args.map is not None:
        check_map_settings(args.map, features, num_words)
    map_images, queries, map_path, extra, title = read_map_and_queries(
        args, features.name, settings=f"words={num_words}|{features}"
    )
    image_paths = [im.path for im in [*map_images, *queries]]
    for option, path in outputs.items():
        check_output_file(path, option, image_paths)
    note(f"map: {len(map_images)} frames -> {map_path}; queries: {len(queries)} frames")
    compile_ahead(steps_for([config]))
    if args.sequential:
        with progress_bar() as update:
            left_out = build_calibrated_map(map_images, map_path, features, num_words, update)
        _map_gravity_warnings(map_path)
        return left_out_exit(
            evaluate_sequential(args, map_path, map_images, queries, config),
            left_out,
            len(map_images),
            "map images",
        )
    results, gravity, left_out = _build_and_localize(
        args, map_images, queries, map_path, features, num_words, config, pairs, gravity
    )
    method, structure = config_label(config)
    summary = summarize(
        results,
        method,
        structure,
        **extra,
        top_n=config.top_n,
        tilt=features.tilt,
        query_gravity="truth" if args.gravity_from_truth else ("file" if gravity else "map"),
    )
    summary["map_images_left_out"] = [{"name": name, "reason": reason} for name, reason in left_out]
    return left_out_exit(
        _report(args, summary, results, map_images, map_path, title), left_out, len(map_images), "map images"
    )


def _map_gravity_warnings(map_path: Path) -> None:
    """The map's gravity warnings (stored with it; they concern the queries without their own
    gravity), once per run: the build only logs them (:func:`planarloc.map.gravity.store_map_gravity`)."""
    with MapDatabase.open(map_path) as db:
        for w in map_gravity(db).warnings:
            note(f"warning: {map_path}: {w}")


def _check_options(args: argparse.Namespace) -> None:
    if args.map_every is not None and args.map_every < 2:
        raise ValueError(f"--map-every must be >= 2 (otherwise there are no queries), got {args.map_every}")
    check_sequential_args(args)
    if args.sequential and (args.ray or args.plot_matches or args.gravity_file or args.gravity_from_truth):
        raise ValueError(
            "--sequential: --ray, --plot-matches and query gravity are single-frame options; drop them"
        )
    if args.ray and (args.plot_matches or args.rerun):
        raise ValueError("--plot-matches and --rerun draw in this process: run them without --ray")


def _check_outputs(args: argparse.Namespace, outputs: dict[str, Path | None]) -> None:
    """The outputs differ from each other and from every input the command line names."""
    _check_distinct(outputs)
    roots = [Path(d) for d in args.dataset] + ([Path(args.queries)] if args.queries is not None else [])
    inputs = input_files(
        [*(f for r in roots for f in dataset_files(r)), *roots, args.pairs, args.gravity_file]
    )
    for option in ("--json", "--plot"):
        check_output_file(outputs[option], option, input_files(inputs, with_map_sidecars=[args.map]))
    check_output_file(args.map, "--map", inputs)


def _build_and_localize(
    args: argparse.Namespace,
    map_images: list,
    queries: list,
    map_path: Path,
    features: FeatureConfig,
    num_words: int,
    config: LocalizerConfig,
    pairs: dict | None,
    gravity: dict | None,
) -> tuple[list, dict | None, list[tuple[str, str]]]:
    """Build (or resume) the map, then localize every query, here or on Ray; returns the results,
    the query gravity used and the map images left out (name, reason)."""
    outputs = EstimateOutputs(args.plot_matches, args.rerun)
    with closing(outputs), ray_session(args.ray) as ray_backend, progress_bar() as update:
        left_out = build_calibrated_map(
            map_images,
            map_path,
            features,
            num_words,
            update,
            mapper=ray_backend.map if ray_backend else None,
        )
        if args.gravity_from_truth:
            # the dataset's declared down direction, else the map's (estimated) gravity
            with MapDatabase.open(map_path) as db:
                gravity = gravity_from_truth(queries, map_gravity(db).g_world_array)
        else:  # queries without their own gravity get the map cameras' mount tilt
            _map_gravity_warnings(map_path)
        progress = lambda d, n: update("localize", d, n)  # noqa: E731
        if ray_backend:
            results = ray_backend.evaluate(map_path, config, queries, pairs, progress, gravity=gravity)
        else:
            results = evaluate_queries(
                Localizer(map_path, config),
                queries,
                progress,
                pairs,
                outputs if outputs.active else None,
                gravity=gravity,
            )
    return results, gravity, left_out


def _report(
    args: argparse.Namespace, summary: dict, results: list, map_images: list, map_path: Path, title: str
) -> int:
    """The table (stdout), the JSON, the TUM files and the plot; the exit code (3: queries not processed)."""
    if args.tum:
        summary["evo"] = write_evaluation_tum(args.tum, results)
    print_summary_table([summary], title)
    write_json(args.json, summary)
    if args.plot:
        with MapDatabase.open(map_path) as db:
            g_world = map_gravity(db).g_world_array
        write_trajectory_plot(
            args.plot, map_images, results, f"{title}: {summary['method']}, {summary['structure']}", g_world
        )
    return partial_exit(results, "queries")


def _check_distinct(outputs: dict[str, Path | None]) -> None:
    seen: dict[str, str] = {}
    for option, path in outputs.items():
        if path is None:
            continue
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{option} {path}: the same path as {seen[key]}; give each output its own path")
        seen[key] = option
