"""The sequential modes of `planarloc localize --sequence` and `planarloc evaluate --sequential`:
their options (defaults from :class:`SequenceConfig`), the evaluation run and its result table.
(`localize --sequence` runs in :mod:`planarloc.cli.localize_command`, like the other localize paths.)"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from rich.table import Table

from planarloc.cli.console import info, progress_bar
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
    info(table)


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
