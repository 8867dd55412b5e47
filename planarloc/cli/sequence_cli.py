"""The sequential modes of `planarloc localize --sequence` and `planarloc evaluate --sequential`:
their options (defaults from :class:`SequenceConfig`), the evaluation run and its result table.
(`localize --sequence` runs in :mod:`planarloc.cli.localize_command`, like the other localize paths.)"""

from __future__ import annotations

import argparse
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.table import Table

from planarloc.cli.console import info, progress_bar
from planarloc.cli.options import add_number
from planarloc.io.results import PREDICTED_MODES
from planarloc.localize.sequence import SequenceLocalizer
from planarloc.localize.stream_config import FIX_MODES, SHARED_SETTINGS, SequenceConfig, sequence_config_from
from planarloc.robust.options import Structure
from planarloc.robust.relative_pose import MODELS

if TYPE_CHECKING:
    from planarloc.geometry.pose import Pose
    from planarloc.localize.localizer import Localizer, LocalizerConfig
    from planarloc.viz.rerun_log import RerunLogger

_SEQ = SequenceConfig()
FIX_DELAY_HELP = "--fixes wait: frames between a fix and its fusion, as a worker would deliver it"


def add_sequence_args(p: argparse.ArgumentParser, evaluate: bool) -> None:
    g = p.add_argument_group("sequential localization")
    _add_stream_source_args(g, evaluate)
    _add_stream_motion_args(g)


def _add_stream_source_args(g: argparse._ArgumentGroup, evaluate: bool) -> None:
    """What makes the stream: `evaluate --sequential` (its simulated stream) or `localize --sequence`."""
    if evaluate:
        g.add_argument(
            "--sequential",
            action="store_true",
            help="stream the query frames in order through the sequential localizer (frame-to-frame "
            "tracking, absolute fixes in the background, pose-graph fusion, kidnap recovery); every "
            "frame is counted, with frames/s and latency",
        )
        g.add_argument(
            "--simulate-odometry",
            action="store_true",
            help="wheel odometry simulated from the ground truth (3%% of distance, 0.3° per axis noise)",
        )
        g.add_argument(
            "--kidnap-at",
            type=int,
            metavar="K",
            help="carry the robot away after the K-th streamed frame and back later (two kidnaps; every "
            "frame still streamed once)",
        )
        g.add_argument("--drop-every", type=int, metavar="N", help="drop every N-th streamed frame")
        g.add_argument(
            "--rate",
            type=float,
            metavar="HZ",
            help="frames arrive at this rate like a camera's (one waiting frame; a newer one replaces "
            "it and the older is counted dropped); default: each frame as soon as the previous "
            "pose is out (the sustained rate)",
        )
    else:
        g.add_argument(
            "--sequence",
            action="store_true",
            help="the images are one ordered stream (files in the given order, folders sorted, or one "
            "image-list file 'path' / 'timestamp path' per line)",
        )
        add_number(
            g,
            "--frame-period",
            float,
            _SEQ.frame_period_s,
            "seconds between frames when the list has no timestamps",
        )
        g.add_argument(
            "--predicted",
            choices=PREDICTED_MODES,
            default=PREDICTED_MODES[0],
            help="predicted frames (carried by the motion model, not fixed at their own time) in the "
            "--out and --tum pose files: 'mark' them with a '# predicted NAME position_std_m=S' "
            "comment line before the pose, or 'drop' them; the JSON records keep every frame "
            "(default: %(default)s)",
        )


def _add_stream_motion_args(g: argparse._ArgumentGroup) -> None:
    """The stream's motion sources, fixes and kidnap handling (both commands)."""
    g.add_argument(
        "--odometry",
        type=Path,
        help="wheel odometry, TUM layout 'timestamp tx ty tz qx qy qz qw' "
        "(camera-to-odometry), one line per frame or matched by timestamp",
    )
    g.add_argument(
        "--fixes",
        choices=FIX_MODES,
        default=_SEQ.fixes,
        help="absolute fixes in a background worker (camera rate) or inside each frame's step (wait: "
        "deterministic, for reproducible offline runs) (default: %(default)s)",
    )
    for flag, field, text in (
        ("--fix-every", "fix_every", "frames between two absolute fixes at least"),
        ("--fix-delay", "fix_delay", FIX_DELAY_HELP),
        ("--window", "window", "poses in the sliding window"),
        ("--local-top-n", "local_top_n", "map images nearest to the prediction used per frame"),
    ):
        add_number(g, flag, int, getattr(_SEQ, field), text)
    g.add_argument(
        "--vo-model",
        default=_SEQ.vo_model,
        choices=MODELS,
        help="visual-odometry motion model (default: %(default)s)",
    )
    g.add_argument(
        "--kidnap-confirmations",
        type=int,
        default=_SEQ.kidnap_confirmations,
        help="consistent contradicting fixes that re-initialise the stream (default: %(default)s)",
    )


def sequence_config(args: argparse.Namespace) -> SequenceConfig:
    """The stream's :class:`SequenceConfig` of the sequential options."""
    kw = {} if getattr(args, "frame_period", None) is None else {"frame_period_s": args.frame_period}
    return sequence_config_from(args, (*SHARED_SETTINGS, "fix_every", "fix_delay"), **kw)


def check_stream_args(args: argparse.Namespace, stream: bool, flag: str) -> None:
    """The stream options are only used with ``flag`` (``--sequence`` / ``--sequential``);
    ``--fix-delay`` only with ``--fixes wait``."""
    defaults = {
        "--fixes": ("fixes", _SEQ.fixes),
        "--fix-every": ("fix_every", _SEQ.fix_every),
        "--fix-delay": ("fix_delay", _SEQ.fix_delay),
    }
    if not stream:
        used = [o for o, (name, default) in defaults.items() if getattr(args, name) != default]
        if args.odometry:
            used.insert(0, "--odometry")
        if used:
            raise ValueError(f"{used[0]}: only used with {flag}")
        return
    if args.fix_delay != _SEQ.fix_delay and args.fixes != "wait":
        raise ValueError(
            "--fix-delay: only used with --fixes wait (background fixes arrive when they are done)"
        )


def print_sequence_table(summaries: list[tuple[str, dict]], title: str) -> None:
    """One row per run: success over every frame, statuses, confident-wrong, relocalization, speed."""
    if not summaries:
        return
    table = Table(title=title, min_width=100)
    table.add_column("run")
    for key in summaries[0][1]["success"]:
        table.add_column(key, justify="right")
    for col in (
        "localized/predicted/lost",
        "confident wrong",
        "rejected",
        "first correct",
        "after kidnap",
        "frames/s",
        "latency p50/p99 [ms]",
        "late/dropped",
    ):
        table.add_column(col, justify="right")
    for label, s in summaries:
        c, reloc = s["status_counts"], s["relocalization"]
        start = "-" if reloc["start"] is None else str(reloc["start"]["frames"])
        kid = reloc["kidnaps"]
        after = "-" if not kid else ", ".join("never" if k is None else str(k["frames"]) for k in kid)
        fps, lat = s["frames_per_second"], s["latency_ms"]
        table.add_row(
            label,
            *[f"{v:.1f}%" for v in s["success"].values()],
            f"{c.get('localized', 0)}/{c.get('predicted', 0)}/{c.get('lost', 0)}",
            str(s["confident_wrong"]),
            str(s["rejected_fixes"]),
            start,
            after,
            "-" if fps is None else f"{fps:.2f}",
            "-" if lat is None else f"{lat['p50']:.0f}/{lat['p99']:.0f}",
            f"{s['late_frames']}/{s['dropped_frames']}",
        )
    info(table)


def check_sequential_args(args: argparse.Namespace) -> None:
    """Reject option combinations of `evaluate` before any work is done."""
    check_stream_args(args, args.sequential, "--sequential")
    if not args.sequential:
        used = [
            o
            for o, v in (
                ("--simulate-odometry", args.simulate_odometry),
                ("--kidnap-at", args.kidnap_at is not None),
                ("--drop-every", args.drop_every is not None),
                ("--rate", args.rate is not None),
            )
            if v
        ]
        if used:
            raise ValueError(f"{used[0]}: only used with --sequential")
        return
    if args.pairs:
        raise ValueError("--pairs: not used with --sequential (retrieval follows the predicted pose)")
    if args.odometry and args.simulate_odometry:
        raise ValueError("--odometry and --simulate-odometry: choose one")
    if args.kidnap_at is not None and args.odometry:
        raise ValueError(
            "--kidnap-at reorders the stream: use it with --simulate-odometry or visual odometry"
        )
    if args.drop_every is not None and args.drop_every < 2:
        raise ValueError(f"--drop-every: expected N >= 2, got {args.drop_every}")
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate: expected a frame rate > 0 (Hz), got {args.rate}")


def evaluate_sequential(
    args: argparse.Namespace,
    map_path: Path,
    map_images: list,
    queries: list,
    localizer_config: LocalizerConfig,
) -> int:
    """`planarloc evaluate --sequential`: the queries in order as one stream; prints and writes the
    summary, the TUM files (``--tum``), the plot (``--plot``) and the Rerun recording (``--rerun``).
    Returns 3 when some frames could not be processed (recorded with status ``error``)."""
    from planarloc.cli.report import partial_exit, write_json, write_trajectory_plot
    from planarloc.cli.result_outputs import write_evaluation_tum
    from planarloc.evaluation.sequence import evaluate_stream, summarize_sequence
    from planarloc.io.odometry import read_odometry
    from planarloc.localize.localizer import Localizer
    from planarloc.localize.records import frame_record
    from planarloc.synthetic.stream import make_stream, stream_order

    n = len(queries)
    drop = range(args.drop_every - 1, n, args.drop_every) if args.drop_every else ()
    order = stream_order(n, kidnap_at=args.kidnap_at, drop=drop)
    frames = make_stream(queries, order, np.random.default_rng(args.seed), frame_period_s=_SEQ.frame_period_s)
    stamps = [f.stamp for f in frames]
    odometry: list[Pose | None] | None
    if args.simulate_odometry:
        odometry = [f.odometry for f in frames]
    elif args.odometry:
        odometry = read_odometry(args.odometry, stamps)
    else:
        odometry = None
    loc = Localizer(map_path, localizer_config)
    with ExitStack() as stack:
        seq = stack.enter_context(SequenceLocalizer(loc, sequence_config(args)))
        seq.warm_up()  # a camera's stream starts on a localizer that is up, not with a slow first frame
        rerun = stream_rerun(args.rerun, loc, stack)
        on_frame = (
            None
            if rerun is None
            else (
                lambda image, est: rerun.log_frame(
                    image.name, frame_record(image.name, est), image.camera, image.path, image.cam_from_world
                )
            )
        )
        with progress_bar() as update:
            results = evaluate_stream(
                seq,
                [f.image for f in frames],
                stamps,
                odometry,
                [f.kidnapped for f in frames],
                lambda d, t: update("localize stream", d, t),
                rate_hz=args.rate,
                on_frame=on_frame,
            )
        stats = vars(seq.stats).copy()
    motion = (
        "simulated odometry" if args.simulate_odometry else "odometry" if args.odometry else "visual odometry"
    )
    summary = summarize_sequence(
        results,
        dataset=" ".join(str(d) for d in args.dataset),
        map_every=args.map_every,
        motion=motion,
        structure=Structure(localizer_config.ransac.structure).value,
        kidnap_at=args.kidnap_at,
        drop_every=args.drop_every,
        dropped=len(drop),
        window=seq.config.window,
        local_top_n=seq.config.local_top_n,
        fixes=seq.config.fixes,
        rate_hz=args.rate,
        stream=stats,
    )
    if args.tum:
        # the dataset's times, also for frames a kidnap re-timed on the stream's clock
        summary["evo"] = write_evaluation_tum(args.tum, results, {q.name: q.timestamp for q in queries})
    split = f"map every {args.map_every}" if args.map_every else f"queries {Path(args.queries).name}"
    title = f"{Path(args.dataset[0]).name}, {split}, {len(frames)} frames streamed"
    print_sequence_table([(motion, summary)], title)
    write_json(args.json, summary)
    write_trajectory_plot(args.plot, map_images, results, f"{title}: {motion}", loc.gravity.g_world_array)
    return partial_exit(results, "frames")


def stream_rerun(path: Path | None, loc: Localizer, stack: ExitStack) -> RerunLogger | None:
    """A Rerun recording of a stream (``--rerun``) with the map logged, closed by ``stack``;
    None without a path."""
    if path is None:
        return None
    from planarloc.viz.rerun_log import RerunLogger

    rerun = RerunLogger(path)

    def close() -> None:
        rerun.close()
        info(f"wrote {rerun.path}")

    stack.callback(close)
    rerun.log_map(loc.map_images)
    return rerun
