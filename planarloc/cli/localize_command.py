"""`planarloc localize`: localize image files against a map."""

from __future__ import annotations

import argparse
import json
import os
from contextlib import closing
from pathlib import Path

from rich.markup import escape

from planarloc.cli.exit_codes import EXIT_OK, EXIT_PARTIAL
from planarloc.cli.map_command import parse_dataset_options
from planarloc.cli.options import (
    add_gravity_file_arg,
    add_localizer_args,
    localizer_config,
    parse_camera,
    parse_gravity,
)
from planarloc.cli.output_paths import check_output_dir, check_output_file, input_files, write_text_atomic
from planarloc.cli.progress import console, progress_bar
from planarloc.cli.query_sources import QuerySource, dataset_queries
from planarloc.cli.remote_localize import add_server_args, run_remote
from planarloc.cli.result_outputs import EstimateOutputs, add_output_args, write_localize_tum
from planarloc.cli.sequence_cli import add_sequence_args, localize_sequence
from planarloc.features.images import read_gray
from planarloc.features.retrieval import retrieve_from_pairs
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import FORMATS
from planarloc.io.gravity_file import read_gravity_file
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.io.pose_list import write_pose_list
from planarloc.localize.localizer import Localizer
from planarloc.localize.records import query_record, query_record_filename
from planarloc.map.schema import MapFormatError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "localize", help="localize query images against a map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Retrieve the top-n map images of each query, match RootSIFT features to them and solve the "
                    "query's absolute pose from 2D-2D matches under local planar motion.\n\n"
                    "Writes the poses of localized queries in the hloc format (name qw qx qy qz tx ty tz, "
                    "world-to-camera) and one JSON per query with its status, inliers and position std. "
                    "Failed queries are listed as failed, never replaced by a map pose. A query that cannot be "
                    "processed (unreadable image, size different from the camera) is recorded as failed with its "
                    "reason and the batch goes on; the results file is always written (exit code 3 then).\n\n"
                    "example:\n  planarloc localize --map kitti.db queries/*.png --camera 'PINHOLE 1241 376 "
                    "718.856 718.856 607.19 185.22' --structure tracks --out poses.txt\n"
                    "  planarloc localize --map office.db frame.png --gravity '0 0.996 0.087'   # camera pitched 5°\n"
                    "  planarloc localize --map office.db run2.bag --format rosbag --dataset-option "
                    "image_topic=/camera/image_raw --tum run2.tum --plot-matches matches/\n"
                    "  planarloc localize --server http://127.0.0.1:8080 --map office frame.png\n"
                    "  planarloc localize --map kitti.db --sequence frames.txt --odometry odom.txt --out poses.txt"
                    "   # a stream: pose, covariance and status (localized/predicted/lost) per frame")
    p.add_argument("--map", required=True, type=Path,
                   help="map file from `planarloc map build` (with --server: the served map's name)")
    p.add_argument("images", nargs="+", type=Path, help="query image files or folders of images, or one dataset "
                                                        "with --format")
    p.add_argument("--format", "-f", choices=sorted(FORMATS), help="read the queries from a dataset in this format "
                   "(e.g. rosbag: images only unless pose options are given; known poses caption --plot-matches)")
    p.add_argument("--dataset-option", action="append", metavar="KEY=VALUE",
                   help="importer option with --format, e.g. image_topic=/cam/image_raw (repeatable)")
    p.add_argument("--camera", help="query intrinsics 'MODEL W H PARAMS...' (COLMAP syntax); default: the map's "
                                    "camera if the map has one camera of the same image size")
    p.add_argument("--out", "-o", type=Path, default=Path("poses.txt"), help="results file (default: %(default)s)")
    p.add_argument("--json-dir", type=Path, help="folder for one JSON per query (default: <out>.json.d)")
    grav = p.add_mutually_exclusive_group()
    grav.add_argument("--gravity", metavar="'GX GY GZ'",
                      help="gravity of all queries (direction, pointing down) in the query camera frame "
                           "(x right, y down, z forward), e.g. from an IMU; default: the map cameras' mount tilt")
    add_gravity_file_arg(grav)
    add_localizer_args(p)
    add_output_args(p, "also write the localized queries as a TUM trajectory (timestamp tx ty tz qx qy qz qw, "
                       "camera-to-world) for evo")
    add_server_args(p)
    add_sequence_args(p, evaluate=False)
    p.set_defaults(func=run)


def _collect(paths: list[Path]) -> list[tuple[str, Path]]:
    out = []
    for p in paths:
        if p.is_dir():
            files = sorted(f for f in p.rglob("*") if f.suffix.lower() in IMAGE_SUFFIXES)
            out += [(str(f.relative_to(p)), f) for f in files]
        elif p.exists():
            out.append((p.name, p))
        else:
            raise ValueError(f"{p}: no such image or folder")
    if not out:
        raise ValueError("no query images found")
    return _unique_names(out)


def _unique_names(items: list[tuple[str, Path]]) -> list[tuple[str, Path]]:
    """Drop repeated files; give different files with the same name (a/1.png, b/1.png) names
    with as many parent folders as it takes to tell them apart, so results never mix up."""
    seen: set[str] = set()
    files = []
    for name, path in items:
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            files.append((name, path))
    names = [n for n, _ in files]
    for depth in range(1, 64):
        counts: dict[str, int] = {}
        for n in names:
            counts[n] = counts.get(n, 0) + 1
        clash = {n for n, c in counts.items() if c > 1}
        if not clash:
            break
        for i, (name, path) in enumerate(files):
            if names[i] in clash:
                parts = Path(os.path.abspath(path)).parts[-depth - 1:]
                names[i] = "/".join(parts) if len(parts) > depth else os.path.abspath(path)
    for n, (_, p) in zip(names, files):
        if any(c.isspace() for c in n):  # before any work: the results file could not hold it
            raise ValueError(f"{p}: query image names must not contain whitespace (the hloc results format "
                             "is 'name qw qx qy qz tx ty tz'); rename the file")
    return [(n, p) for n, (_, p) in zip(names, files)]


def _map_camera(loc: Localizer) -> Camera | None:
    """The map's camera if it has exactly one, else None."""
    cams = {p.camera for p in loc.db.posed_images()}
    return next(iter(cams)) if len(cams) == 1 else None


def _default_camera(loc: Localizer, shape: tuple[int, int]) -> Camera:
    """The map's only camera for a query of image size ``shape`` (H, W); an error otherwise."""
    map_camera = _map_camera(loc)
    if map_camera is None:
        raise ValueError("the map has several cameras: pass the query intrinsics with --camera")
    return _query_camera(None, map_camera, shape, False)


def _query_camera(camera: Camera | None, map_camera: Camera, shape: tuple[int, int], given: bool) -> Camera:
    cam = camera or map_camera
    if (cam.height, cam.width) != shape:
        source = "--camera" if given else "the map camera"
        raise InputError(f"image is {shape[1]}x{shape[0]} but {source} is {cam.width}x{cam.height}"
                         + ("" if given else "; pass --camera"))
    return cam


def _gravity_file_notes(path: Path, gravity: dict, names: set[str]) -> None:
    """Say which queries the gravity file missed and which of its names matched no query."""
    missing, unused = len(names - set(gravity)), sorted(set(gravity) - names)
    if missing:
        console.print(f"[yellow]{path}: no gravity for {missing} of {len(names)} queries; they were assumed "
                      "mounted like the map cameras[/]")
    if unused:
        console.print(f"[yellow]{path}: {len(unused)} name(s) match no query, e.g. {unused[0]!r} "
                      "(names are file names, or paths relative to a query folder)[/]")


def run(args: argparse.Namespace) -> int:
    # Options and outputs are checked before the first image is read.
    if args.sequence:
        if args.server or args.format or args.tum or args.plot_matches or args.rerun or args.gravity_file:
            raise ValueError("--sequence: --server, --format, --tum, --plot-matches, --rerun and --gravity-file are "
                             "single-frame options; drop them")
        check_output_file(args.out, "--out", input_files(list(args.images) + [args.odometry],
                                                         with_map_sidecars=[args.map]))
        return localize_sequence(args)
    if args.odometry:
        raise ValueError("--odometry: only used with --sequence")
    config = localizer_config(args)
    camera = parse_camera(args.camera) if args.camera else None
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    gravity_all = parse_gravity(args.gravity) if args.gravity else None
    gravity = read_gravity_file(args.gravity_file) if args.gravity_file else None
    if args.format:
        queries = dataset_queries(args.images, args.format, parse_dataset_options(args.dataset_option), camera)
    else:
        queries = [QuerySource(name, path) for name, path in _collect(args.images)]
    if args.server:
        return run_remote(args, [(q.name, q.path) for q in queries])
    json_dir = args.json_dir or args.out.with_name(args.out.name + ".json.d")
    inputs = input_files([q.path for q in queries] + [args.pairs, args.gravity_file], with_map_sidecars=[args.map])
    check_output_file(args.out, "--out", inputs)
    check_output_dir(json_dir, "--json-dir", inputs)
    for option in ("tum", "rerun"):
        if getattr(args, option, None) is not None:
            check_output_file(getattr(args, option), f"--{option}", inputs)
    if args.plot_matches is not None:
        check_output_dir(args.plot_matches, "--plot-matches", inputs)
    if _same_path(json_dir, args.out):
        raise ValueError(f"--json-dir {json_dir}: is the same path as --out; choose another folder")
    loc = Localizer(args.map, config)
    map_camera = _map_camera(loc)
    if camera is None and map_camera is None and not all(q.camera is not None for q in queries):
        raise ValueError("the map has several cameras: pass the query intrinsics with --camera")
    if gravity_all is None:
        rep = loc.gravity
        console.print(f"map gravity: {rep.source}; queries without their own gravity are assumed mounted like the "
                      f"map cameras (pitch {rep.pitch_deg:+.1f}°, roll {rep.roll_deg:+.1f}°)",
                      highlight=False, soft_wrap=True)
    json_dir.mkdir(parents=True, exist_ok=True)
    poses, tum, failed, errors = [], [], 0, 0
    outputs = EstimateOutputs(args.plot_matches, args.rerun)
    try:
        with progress_bar() as update, closing(outputs):
            for i, q in enumerate(queries):
                name, path = q.name, q.path
                g = gravity_all if gravity is None else gravity.get(name)
                try:  # one bad query is recorded as failed with its reason; the batch goes on
                    image = read_gray(path)
                    given = camera is not None or q.camera is not None
                    cam = _query_camera(camera or q.camera, map_camera, image.shape[:2], given)  # type: ignore[arg-type]
                    refs = retrieve_from_pairs(pairs, name, loc.config.top_n) if pairs else None
                    est = loc.localize(image, cam, refs, gravity=g)
                    outputs.add(loc, name, path, cam, est, q.truth)
                    record = query_record(name, est, g)
                except MapFormatError:
                    raise  # a damaged map fails every query: stop (the results so far are written)
                except (InputError, OSError) as exc:
                    reason = f"{path}: {exc.strerror or exc}" if isinstance(exc, OSError) else str(exc)
                    est, record = None, {"name": name, "success": False, "status": "error", "reason": reason}
                    errors += 1
                    console.print(f"[yellow]query {escape(name)} not processed:[/] {escape(reason)}")
                write_text_atomic(json_dir / query_record_filename(name), json.dumps(record, indent=1))
                if est is not None and est.success:
                    poses.append((name, est.pose))
                    tum.append((name, q.timestamp, est.pose))
                else:
                    failed += 1
                update("localize", i + 1, len(queries))
    finally:
        write_pose_list(args.out, poses)  # always written, also when interrupted (atomic)
        if args.tum:
            write_localize_tum(args.tum, tum)
    if gravity is not None:
        _gravity_file_notes(args.gravity_file, gravity, {q.name for q in queries})
    ours = {query_record_filename(q.name) for q in queries}
    stale = [p.name for p in json_dir.glob("*.json") if p.name not in ours]
    if stale:
        console.print(f"[yellow]note:[/] {len(stale)} JSON file(s) in {json_dir}/ are from an earlier run (e.g. "
                      f"{stale[0]}), not from these queries")
    console.print(f"localized {len(poses)} of {len(queries)} queries ({failed} failed"
                  f"{f', {errors} could not be processed' if errors else ''}) -> {args.out}, details in {json_dir}/")
    return EXIT_PARTIAL if errors else EXIT_OK


def _same_path(a: Path, b: Path) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)
