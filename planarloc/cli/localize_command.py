"""`planarloc localize`: localize image files against a map — one by one (batch), as one stream
(``--sequence``) or through a running service (``--server``).

The three paths are one run (:func:`run_queries`): the same queries and names
(:mod:`planarloc.cli.query_sources`), one record per query or frame and one results file written
by the same writer (:class:`planarloc.io.results.ResultsWriter`), the same exit codes. A query
that cannot be processed (an unreadable image, a size different from its camera's) is recorded
with status ``error`` and its reason, the others go on, and the exit code is 3. An error that
concerns the whole run (a damaged map, an unreachable server, an unwritable folder) stops it with
exit code 1 and leaves an earlier results file as it was. Ctrl-C writes the results of the queries
done so far and says so (exit code 130).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from contextlib import ExitStack, closing
from dataclasses import replace
from itertools import pairwise
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note, progress_bar, results_on_stdout
from planarloc.cli.exit_codes import EXIT_OK, EXIT_PARTIAL, Interrupted
from planarloc.cli.options import (
    add_gravity_args,
    add_localizer_args,
    add_map_features_arg,
    camera_option,
    check_map_features,
    gravity_option,
    localizer_config_of,
    parse_dataset_options,
)
from planarloc.cli.query_sources import QuerySource, dataset_queries, image_queries, list_queries
from planarloc.cli.remote_localize import add_server_args, check_remote_args, remote_localizer
from planarloc.cli.result_outputs import EstimateOutputs, add_output_args
from planarloc.cli.sequence_cli import add_sequence_args, check_stream_args, sequence_config, stream_rerun
from planarloc.cli.warmup_command import first_use
from planarloc.compile import steps_for
from planarloc.compile.first_use import COMPILE_CHOICES, COMPILE_ENV
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import FORMATS
from planarloc.io.gravity_file import read_gravity_file
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.io.kitti import kitti_frame_times
from planarloc.io.output import STDOUT, check_output_dir, check_output_file, input_files
from planarloc.io.results import ResultsWriter, default_records_dir
from planarloc.localize.localizer import Localizer
from planarloc.localize.records import error_record, frame_record, query_record
from planarloc.map.schema import MapFormatError

#: ``localize(query) -> record`` of one path (batch, stream, server).
LocalizeOne = Callable[[QuerySource], dict]

#: ``--compile auto``: run as Python while compiling in the background up to this many queries.
#: Measured on KITTI seq 2 (a 13-image map, 2 cores, empty cache): 12 queries take 52.4 s as
#: Python with the compile in the background (the first 10-12 s with the hot kernels' compile,
#: the next about 3.7 s each; the compile alone 92 s on one core) and 54.1 s compiling first
#: (48 s on both cores, then about 0.5 s per query): even at about 12, compiling first wins beyond.
AUTO_BACKGROUND = 12


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "localize",
        "localize query images against a map",
        """Retrieve the top-n map images of each query, match RootSIFT features to them and solve the query's
        absolute pose from 2D-2D matches under local planar motion.

        Writes the poses of localized queries in the hloc format (name qw qx qy qz tx ty tz, world-to-camera)
        to --out ('-' = stdout; a device or FIFO is written through; an existing file that is not a results
        file is refused) and one JSON record per query with its status, inliers and position std. Failed
        queries are listed as failed, never replaced by a map pose. A query that cannot be processed
        (unreadable image, size different from the camera) is recorded with status error and its reason and
        the others go on (exit code 3); the same holds with --sequence and --server. Query names: the file
        name of an image given directly, the path relative to a folder or dataset given; parent folders are
        added to tell equal names apart.""",
        [
            "planarloc localize --map kitti.db queries/*.png --camera 'PINHOLE 1241 376 718.856 718.856 "
            "607.19 185.22' --structure tracks --out poses.txt",
            "planarloc localize --map office.db frame.png --gravity '0 0.996 0.087'   # camera pitched 5°",
            "planarloc localize --map office.db run2.bag --format rosbag --dataset-option "
            "image_topic=/camera/image_raw --tum run2.tum --plot-matches matches/",
            "planarloc localize --server http://127.0.0.1:8080 --map office frame.png --out -",
            "planarloc localize --map kitti.db --sequence frames.txt --odometry odom.txt --out poses.txt"
            "   # a stream: pose, covariance and status (localized/predicted/lost) per frame",
        ],
        run,
        interrupted=None,
    )
    _add_input_args(p)
    add_gravity_args(
        p,
        "--gravity",
        metavar="'GX GY GZ'",
        help="gravity of all queries (direction, pointing down) in the query camera frame (x right, "
        "y down, z forward), e.g. from an IMU; default: the map cameras' mount tilt",
    )
    add_localizer_args(p)
    add_map_features_arg(p)
    add_output_args(
        p,
        "also write the localized queries as a TUM trajectory (timestamp tx ty tz qx qy qz qw, "
        "camera-to-world) for evo",
    )
    add_server_args(p)
    add_sequence_args(p, evaluate=False)
    p.add_argument(
        "--compile",
        choices=COMPILE_CHOICES,
        default=os.environ.get(COMPILE_ENV, "auto"),
        help="when planarloc's kernels are not compiled yet (no `planarloc warmup`): compile them in a "
        "detached process and run the queries meanwhile as Python, slower (background: a first pose in "
        f"seconds), or compile on every core first (wait); auto: background for up to {AUTO_BACKGROUND} "
        f"queries (default: %(default)s, or ${COMPILE_ENV})",
    )


def _add_input_args(p: argparse.ArgumentParser) -> None:
    """The map, the queries (files, folders or a dataset), their camera and the outputs."""
    p.add_argument(
        "--map",
        required=True,
        type=Path,
        help="map file from `planarloc map build` (with --server: the served map's name)",
    )
    p.add_argument(
        "images",
        nargs="+",
        type=Path,
        help="query image files or folders of images, or one dataset with --format",
    )
    p.add_argument(
        "--format",
        "-f",
        choices=sorted(FORMATS),
        help="read the queries from a dataset in this format "
        "(e.g. rosbag: images only unless pose options are given; known poses caption --plot-matches)",
    )
    p.add_argument(
        "--dataset-option",
        action="append",
        metavar="KEY=VALUE",
        help="importer option with --format, e.g. image_topic=/cam/image_raw (repeatable)",
    )
    p.add_argument(
        "--camera",
        help="query intrinsics 'MODEL W H PARAMS...' (COLMAP syntax); default: the map's "
        "camera if the map has one camera of the same image size",
    )
    p.add_argument(
        "--out", "-o", default="poses.txt", help="results file, '-' for stdout (default: %(default)s)"
    )
    p.add_argument(
        "--json-dir",
        type=Path,
        help="folder for one JSON record per query (default: <out>.json.d; none with --out - "
        "or a device unless given)",
    )


def _check_outputs(args: argparse.Namespace, inputs: list[Path]) -> Path | None:
    """Every output of the run is checked here, before any work; returns the records folder."""
    check_output_file(args.out, "--out", inputs, results=True)
    records_dir = args.json_dir if args.json_dir is not None else default_records_dir(args.out)
    check_output_dir(records_dir, "--json-dir", inputs)
    if records_dir is not None and str(args.out) != STDOUT and _same_path(records_dir, Path(args.out)):
        raise ValueError(f"--json-dir {records_dir}: is the same path as --out; choose another folder")
    check_output_file(args.tum, "--tum", inputs, results=True)
    check_output_file(args.rerun, "--rerun", inputs)
    check_output_dir(args.plot_matches, "--plot-matches", inputs)
    if str(args.out) == STDOUT:
        results_on_stdout()
    return records_dir


def _queries(args: argparse.Namespace, camera: Camera | None) -> tuple[list[QuerySource], bool]:
    """The run's queries (named by the naming rule) and whether their stamps came from an image list."""
    if args.format:
        options = parse_dataset_options(args.dataset_option, fmt=args.format)
        return dataset_queries(args.images, args.format, options, camera), False
    if (
        args.sequence
        and len(args.images) == 1
        and args.images[0].is_file()
        and args.images[0].suffix.lower() == ".txt"
    ):
        queries, timed = list_queries(args.images[0], args.frame_period)
        return (queries if timed else _with_source_times(queries, stream=True)), timed
    if args.sequence:
        files = [p for p in args.images if not p.is_dir()]
        seen: dict[str, Path] = {}
        for p in files:
            if os.path.realpath(p) in seen:
                raise ValueError(
                    f"--sequence: {p} is given twice (as {seen[os.path.realpath(p)]} before); a stream "
                    "shows each frame once"
                )
            seen[os.path.realpath(p)] = p
    queries = image_queries(args.images)
    if args.sequence:
        queries = [
            QuerySource(q.name, q.path, timestamp=k * args.frame_period) for k, q in enumerate(queries)
        ]
    return _with_source_times(queries, stream=args.sequence), False


def _with_source_times(queries: list[QuerySource], stream: bool) -> list[QuerySource]:
    """Queries that are the frames of a KITTI sequence with ``times.txt`` get its stamps (the TUM
    file's times, the stream's clock); a stream only if they increase in the given order."""
    times = kitti_frame_times([q.path for q in queries])
    if times is None or (stream and any(b <= a for a, b in pairwise(times))):
        return queries
    return [replace(q, timestamp=t) for q, t in zip(queries, times)]


def _check_options(args: argparse.Namespace) -> None:
    """Option combinations, refused before any work."""
    if args.compile not in COMPILE_CHOICES:  # argparse checks a given --compile, not its default
        raise ValueError(
            f"{COMPILE_ENV}={args.compile!r}: expected one of {', '.join(COMPILE_CHOICES)} "
            "(the default of --compile)"
        )
    check_stream_args(args, args.sequence, "--sequence")
    if args.sequence:
        used = [
            o
            for o, v in (
                ("--server", args.server),
                ("--format", args.format),
                ("--plot-matches", args.plot_matches),
                ("--gravity-file", args.gravity_file),
                ("--pairs", args.pairs),
            )
            if v
        ]
        if used:
            raise ValueError(
                f"--sequence: {', '.join(used)} are single-frame options; drop them (retrieval and "
                "gravity follow the stream)"
            )
    if args.server:
        check_remote_args(args)


def run(args: argparse.Namespace) -> int:
    # Options, inputs and outputs are checked before the first image is read.
    _check_options(args)
    camera = camera_option(args.camera)
    gravity = gravity_option(args.gravity)
    gravity_file = read_gravity_file(args.gravity_file) if args.gravity_file else None
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    queries, timed = _queries(args, camera)
    inputs = input_files(
        [q.path for q in queries] + [args.pairs, args.gravity_file, args.odometry, *args.images],
        with_map_sidecars=[] if args.server else [args.map],
    )
    records_dir = _check_outputs(args, inputs)
    with ExitStack() as stack:
        if args.server:
            from planarloc.client import Client, resolve_token

            client = stack.enter_context(
                Client(args.server, token=resolve_token(args.token, args.token_file))
            )
            localize = remote_localizer(client, args, camera, gravity)
            where = f" via {args.server}"
        else:
            loc = Localizer(args.map, localizer_config_of(args))
            check_map_features(args.map, loc.features.kind, args.features)
            wait = args.compile == "wait" or (args.compile == "auto" and len(queries) > AUTO_BACKGROUND)
            poll_compile = stack.enter_context(first_use(steps_for([loc.config]), wait=wait))
            if camera is None and len(loc.map_cameras) != 1 and not all(q.camera for q in queries):
                raise ValueError(
                    f"the map has {len(loc.map_cameras)} cameras: pass the query intrinsics with --camera"
                )
            if gravity is None and gravity_file is None:
                rep = loc.gravity
                note(
                    f"map gravity: {rep.source}; queries without their own gravity are assumed mounted like "
                    f"the map cameras (pitch {rep.pitch_deg:+.1f}°, roll {rep.roll_deg:+.1f}°)"
                )
            if args.sequence:
                each = _stream_localizer(loc, args, camera, gravity, queries, timed, stack)
            else:
                outputs = stack.enter_context(closing(EstimateOutputs(args.plot_matches, args.rerun)))
                each = _batch_localizer(loc, camera, gravity, gravity_file, pairs, outputs)
            localize = _then(each, poll_compile)
            where = ""
        writer = ResultsWriter(
            args.out, records_dir, tum=args.tum, predicted=getattr(args, "predicted", "mark")
        )
        code = run_queries(writer, queries, localize, "localize stream" if args.sequence else "localize")
    if gravity_file is not None:
        _gravity_file_notes(args.gravity_file, gravity_file, {q.name for q in queries})
    stale = writer.stale_records()
    if stale:
        note(
            f"note: {len(stale)} JSON file(s) in {records_dir}/ are from an earlier run (e.g. {stale[0]}), "
            "not from these queries"
        )
    _summary(writer, args, records_dir, where)
    return code


def run_queries(writer: ResultsWriter, queries: list[QuerySource], localize: LocalizeOne, stage: str) -> int:
    """Localize every query in order, recording each; write the results at the end (or when
    interrupted). Returns the exit code: 3 if a query could not be processed, else 0."""
    try:
        with progress_bar() as update:
            update(stage, 0, len(queries))  # the bar's time starts with the first query
            for i, q in enumerate(queries):
                record = localize(q)
                if record["status"] == "error":
                    note(f"query {q.name} not processed: {record['message']}")
                writer.add(record, q.timestamp)
                update(stage, i + 1, len(queries))
    except KeyboardInterrupt:
        writer.close()
        where = "on stdout" if str(writer.out) == STDOUT else f"in {writer.out}"
        raise Interrupted(
            f"interrupted after {writer.queries} of {len(queries)} queries: their results are {where} "
            f"(the others have none); re-running the command localizes all {len(queries)} again"
        ) from None
    except BaseException:
        writer.abort()  # a failed run: the earlier results file and records stay as they were
        raise
    writer.close()
    return EXIT_PARTIAL if writer.errors else EXIT_OK


def _then(localize: LocalizeOne, after: Callable[[], None]) -> LocalizeOne:
    """``localize``, then ``after()`` (between queries: whether the kernels are compiled now)."""

    def each(q: QuerySource) -> dict:
        record = localize(q)
        after()
        return record

    return each


def _batch_localizer(
    loc: Localizer,
    camera: Camera | None,
    gravity: object | None,
    gravity_file: dict | None,
    pairs: dict | None,
    outputs: EstimateOutputs,
) -> LocalizeOne:
    def localize(q: QuerySource) -> dict:
        g = gravity if gravity_file is None else gravity_file.get(q.name)
        try:  # one bad query is recorded with its reason; the batch goes on
            query = loc.prepare(q.path, camera or q.camera, name=q.name, gravity=g, pairs=pairs)
            est = loc.localize_query(query)
            outputs.add(loc, q.name, q.path, query.camera, est, q.truth)
        except MapFormatError:
            raise  # a damaged map fails every query: stop
        except (InputError, OSError) as exc:
            return error_record(
                q.name,
                f"{q.path}: {exc.strerror or exc}" if isinstance(exc, OSError) else str(exc),
                stamp=q.timestamp,
            )
        return query_record(q.name, est, query.gravity, stamp=q.timestamp)

    return localize


def _stream_localizer(
    loc: Localizer,
    args: argparse.Namespace,
    camera: Camera | None,
    gravity: object | None,
    queries: list[QuerySource],
    timed: bool,
    stack: ExitStack,
) -> LocalizeOne:
    from planarloc.io.odometry import read_odometry
    from planarloc.localize.sequence import SequenceLocalizer

    # timed: every query has its time (from the image list); otherwise the odometry is one line per frame
    stamps = [q.timestamp for q in queries if q.timestamp is not None] if timed else None
    odometry = read_odometry(args.odometry, stamps) if args.odometry else None
    if odometry is not None and len(odometry) != len(queries):
        raise ValueError(
            f"{args.odometry}: {len(odometry)} odometry poses for {len(queries)} frames (without "
            "timestamps in the image list the file must have one line per frame)"
        )
    seq = stack.enter_context(SequenceLocalizer(loc, sequence_config(args)))
    rerun = stream_rerun(args.rerun, loc, stack)
    frames = iter(range(len(queries)))  # the run localizes the queries once, in order

    def localize(q: QuerySource) -> dict:
        k = next(frames)
        try:  # one bad frame is recorded with its reason; the stream goes on
            if q.timestamp is None:
                raise InputError(f"{q.path}: a frame of a stream needs a time")
            query = loc.prepare(q.path, camera, name=q.name, gravity=gravity)
            est = seq.step_query(query, float(q.timestamp), None if odometry is None else odometry[k])
        except MapFormatError:
            raise
        except (InputError, OSError) as exc:
            reason = f"{q.path}: {exc.strerror or exc}" if isinstance(exc, OSError) else str(exc)
            return error_record(q.name, reason, kind="frame", stamp=q.timestamp)
        record = frame_record(q.name, est)
        if rerun is not None:
            rerun.log_frame(q.name, record, query.camera, q.path)
        return record

    return localize


def _summary(writer: ResultsWriter, args: argparse.Namespace, records_dir: Path | None, where: str) -> None:
    details = f", records in {records_dir}/" if records_dir is not None else ""
    errors = f", {writer.errors} could not be processed" if writer.errors else ""
    if args.sequence:
        counts = ", ".join(f"{v} {k}" for k, v in sorted(writer.statuses.items()))
        kept = (
            "localized poses; predicted ones dropped"
            if writer.predicted == "drop"
            else "localized poses, predicted ones marked '# predicted'"
        )
        info(f"{writer.queries} frames: {counts} -> {args.out} ({kept}){details}")
    else:
        failed = writer.queries - writer.localized
        info(
            f"localized {writer.localized} of {writer.queries} queries ({failed} failed{errors}){where} -> "
            f"{args.out}{details}"
        )


def _gravity_file_notes(path: Path, gravity: dict, names: set[str]) -> None:
    """Say which queries the gravity file missed and which of its names matched no query."""
    missing, unused = len(names - set(gravity)), sorted(set(gravity) - names)
    if missing:
        note(
            f"{path}: no gravity for {missing} of {len(names)} queries; they were assumed mounted like the "
            "map cameras"
        )
    if unused:
        note(
            f"{path}: {len(unused)} name(s) match no query, e.g. {unused[0]!r} (names follow the query "
            "naming rule: file names, or paths relative to a query folder)"
        )


def _same_path(a: Path, b: Path) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)
