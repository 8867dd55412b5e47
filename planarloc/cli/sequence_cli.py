"""The sequential modes of `planarloc localize --sequence` and `planarloc evaluate --sequential`:
their options (defaults from :class:`SequenceConfig`), runs and result table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.table import Table

from planarloc.cli.progress import console, progress_bar
from planarloc.localize.sequence import SequenceConfig, SequenceLocalizer
from planarloc.robust.relative_pose import MODELS

_SEQ = SequenceConfig()


def add_sequence_args(p: argparse.ArgumentParser, evaluate: bool) -> None:
    g = p.add_argument_group("sequential localization")
    if evaluate:
        g.add_argument("--sequential", action="store_true",
                       help="stream the query frames in order through the sequential localizer (odometry or visual "
                            "odometry, gating, pose-graph fusion, kidnap recovery); every frame is counted")
        g.add_argument("--simulate-odometry", action="store_true",
                       help="wheel odometry simulated from the ground truth (3%% of distance, 0.3° per axis noise)")
        g.add_argument("--kidnap-at", type=int, metavar="K",
                       help="carry the robot away after the K-th streamed frame and back later (two kidnaps; every "
                            "frame still streamed once)")
        g.add_argument("--drop-every", type=int, metavar="N", help="drop every N-th streamed frame")
    else:
        g.add_argument("--sequence", action="store_true",
                       help="the images are one ordered stream (files in the given order, folders sorted, or one "
                            "image-list file 'path' / 'timestamp path' per line)")
        g.add_argument("--frame-period", type=float, default=_SEQ.frame_period_s,
                       help="seconds between frames when the list has no timestamps (default: %(default)s)")
    g.add_argument("--odometry", type=Path, help="wheel odometry, TUM layout 'timestamp tx ty tz qx qy qz qw' "
                                                 "(camera-to-odometry), one line per frame or matched by timestamp")
    g.add_argument("--window", type=int, default=_SEQ.window, help="poses in the sliding window (default: %(default)s)")
    g.add_argument("--local-top-n", type=int, default=_SEQ.local_top_n,
                   help="map images nearest to the prediction used per frame (default: %(default)s)")
    g.add_argument("--vo-model", default=_SEQ.vo_model, choices=MODELS,
                   help="visual-odometry motion model (default: %(default)s)")
    g.add_argument("--kidnap-confirmations", type=int, default=_SEQ.kidnap_confirmations,
                   help="consistent contradicting fixes that re-initialise the stream (default: %(default)s)")


def sequence_config(args: argparse.Namespace) -> SequenceConfig:
    kw = {}
    if getattr(args, "frame_period", None) is not None:
        kw["frame_period_s"] = args.frame_period
    return SequenceConfig(window=args.window, local_top_n=args.local_top_n, vo_model=args.vo_model,
                          kidnap_confirmations=args.kidnap_confirmations, **kw)


def print_sequence_table(summaries: list[tuple[str, dict]], title: str) -> None:
    """One row per run: success over every frame, statuses, confident-wrong, relocalization, speed."""
    if not summaries:
        return
    table = Table(title=title, min_width=100)
    table.add_column("run")
    for key in summaries[0][1]["success"]:
        table.add_column(key, justify="right")
    for col in ("localized/predicted/lost", "confident wrong", "rejected", "first correct", "after kidnap", "frames/s"):
        table.add_column(col, justify="right")
    for label, s in summaries:
        c, reloc = s["status_counts"], s["relocalization"]
        start = "-" if reloc["start"] is None else str(reloc["start"]["frames"])
        kid = reloc["kidnaps"]
        after = "-" if not kid else ", ".join("never" if k is None else str(k["frames"]) for k in kid)
        fps = s["frames_per_second"]
        table.add_row(label, *[f"{v:.1f}%" for v in s["success"].values()],
                      f"{c.get('localized', 0)}/{c.get('predicted', 0)}/{c.get('lost', 0)}",
                      str(s["confident_wrong"]), str(s["rejected_fixes"]), start, after,
                      "-" if fps is None else f"{fps:.2f}")
    console.print(table)


def _stream_inputs(args: argparse.Namespace) -> tuple[list[str], list[Path], list[float], bool]:
    """Names, paths and stamps of the stream, and whether the stamps came from the list."""
    from planarloc.cli.localize_command import _collect
    from planarloc.io.odometry import read_image_list

    if len(args.images) == 1 and args.images[0].is_file() and args.images[0].suffix.lower() == ".txt":
        entries = read_image_list(args.images[0])
        paths = [p for _, p in entries]
        names = [str(p.relative_to(args.images[0].parent)) if p.is_relative_to(args.images[0].parent) else p.name
                 for p in paths]
        if entries[0][0] is not None:
            stamps = [float(s) for s, _ in entries]
            if np.any(np.diff(stamps) <= 0):
                raise ValueError(f"{args.images[0]}: timestamps must increase along the list")
            return names, paths, stamps, True
    else:
        named = _collect(args.images)
        names, paths = [n for n, _ in named], [p for _, p in named]
    return names, paths, [k * args.frame_period for k in range(len(paths))], False


def localize_sequence(args: argparse.Namespace) -> int:
    """`planarloc localize --sequence`: one pose, covariance and status per frame."""
    from planarloc.cli.localize_command import _default_camera
    from planarloc.cli.options import localizer_config, parse_camera
    from planarloc.features.images import read_gray
    from planarloc.io.odometry import read_odometry
    from planarloc.io.pose_list import write_pose_list
    from planarloc.localize.localizer import Localizer

    if args.pairs:
        raise ValueError("--pairs: not used with --sequence (retrieval follows the predicted pose)")
    names, paths, stamps, timed = _stream_inputs(args)
    config = sequence_config(args)
    odometry = read_odometry(args.odometry, stamps if timed else None) if args.odometry else None
    if odometry is not None and len(odometry) != len(paths):
        raise ValueError(f"{args.odometry}: {len(odometry)} odometry poses for {len(paths)} frames (without "
                         "timestamps in the image list the file must have one line per frame)")
    seq = SequenceLocalizer(Localizer(args.map, localizer_config(args)), config)
    json_dir = args.json_dir or args.out.with_name(args.out.name + ".json.d")
    json_dir.mkdir(parents=True, exist_ok=True)
    camera = parse_camera(args.camera) if args.camera else None
    poses, counts = [], {}
    with progress_bar() as update:
        for k, (name, path) in enumerate(zip(names, paths)):
            image = read_gray(path)
            cam = camera or _default_camera(seq.localizer, image.shape[:2])
            est = seq.step(image, cam, stamps[k], None if odometry is None else odometry[k])
            (json_dir / (name.replace("/", "__") + ".json")).write_text(json.dumps({"name": name, **est.to_dict()},
                                                                                  indent=1))
            counts[est.status] = counts.get(est.status, 0) + 1
            if est.success:
                poses.append((name, est.pose))
            update("localize stream", k + 1, len(paths))
    write_pose_list(args.out, poses)
    console.print(f"{len(paths)} frames: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) +
                  f" -> {args.out} (localized and predicted poses), status and covariance per frame in {json_dir}/")
    return 0


def check_sequential_args(args: argparse.Namespace) -> None:
    """Reject option combinations of `evaluate` before any work is done."""
    if not args.sequential:
        used = [o for o, v in (("--odometry", args.odometry), ("--simulate-odometry", args.simulate_odometry),
                               ("--kidnap-at", args.kidnap_at is not None),
                               ("--drop-every", args.drop_every is not None)) if v]
        if used:
            raise ValueError(f"{used[0]}: only used with --sequential")
        return
    if args.pairs:
        raise ValueError("--pairs: not used with --sequential (retrieval follows the predicted pose)")
    if args.plot:
        raise ValueError("--plot: not available with --sequential; the JSON (--json) has every frame's pose")
    if args.odometry and args.simulate_odometry:
        raise ValueError("--odometry and --simulate-odometry: choose one")
    if args.kidnap_at is not None and args.odometry:
        raise ValueError("--kidnap-at reorders the stream: use it with --simulate-odometry or visual odometry")
    if args.drop_every is not None and args.drop_every < 2:
        raise ValueError(f"--drop-every: expected N >= 2, got {args.drop_every}")


def evaluate_sequential(args: argparse.Namespace, map_path: Path, queries: list, localizer_config: object) -> int:
    """`planarloc evaluate --sequential`: the queries in order as one stream; prints and writes the summary."""
    from planarloc.cli.report import write_json
    from planarloc.evaluation.sequence import evaluate_stream, summarize_sequence
    from planarloc.io.odometry import read_odometry
    from planarloc.localize.localizer import Localizer
    from planarloc.synthetic.stream import make_stream, stream_order

    n = len(queries)
    drop = range(args.drop_every - 1, n, args.drop_every) if args.drop_every else ()
    order = stream_order(n, kidnap_at=args.kidnap_at, drop=drop)
    frames = make_stream(queries, order, np.random.default_rng(args.seed), frame_period_s=_SEQ.frame_period_s)
    stamps = [f.stamp for f in frames]
    if args.simulate_odometry:
        odometry = [f.odometry for f in frames]
    elif args.odometry:
        odometry = read_odometry(args.odometry, stamps)
    else:
        odometry = None
    seq = SequenceLocalizer(Localizer(map_path, localizer_config), sequence_config(args))
    with progress_bar() as update:
        results = evaluate_stream(seq, [f.image for f in frames], stamps, odometry, [f.kidnapped for f in frames],
                                  lambda d, t: update("localize stream", d, t))
    motion = "simulated odometry" if args.simulate_odometry else "odometry" if args.odometry else "visual odometry"
    summary = summarize_sequence(results, dataset=" ".join(str(d) for d in args.dataset), map_every=args.map_every,
                                 motion=motion,
                                 structure=str(getattr(localizer_config.ransac.structure, "value", "")),
                                 kidnap_at=args.kidnap_at, drop_every=args.drop_every, dropped=len(drop),
                                 window=seq.config.window, local_top_n=seq.config.local_top_n)
    print_sequence_table([(motion, summary)], f"{Path(args.dataset[0]).name}, map every {args.map_every}, "
                                              f"{len(frames)} frames streamed")
    write_json(args.json, summary)
    return 0
