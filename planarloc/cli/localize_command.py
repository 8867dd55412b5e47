"""`planarloc localize`: localize image files against a map."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from planarloc.cli.options import add_localizer_args, localizer_config, parse_camera
from planarloc.cli.progress import console, progress_bar
from planarloc.cli.sequence_cli import add_sequence_args, localize_sequence
from planarloc.geometry.camera import Camera
from planarloc.io.hloc_pairs import read_hloc_pairs
from planarloc.io.pose_list import write_pose_list
from planarloc.pipeline.localizer import Localizer
from planarloc.pipeline.map_builder import read_gray
from planarloc.pipeline.retrieval import retrieve_from_pairs

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "localize", help="localize query images against a map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Retrieve the top-n map images of each query, match RootSIFT features to them and solve the "
                    "query's absolute pose from 2D-2D matches under local planar motion.\n\n"
                    "Writes the poses of localized queries in the hloc format (name qw qx qy qz tx ty tz, "
                    "world-to-camera) and one JSON per query with its status, inliers and position std. "
                    "Failed queries are listed as failed, never replaced by a map pose.\n\n"
                    "example:\n  planarloc localize --map kitti.db queries/*.png --camera 'PINHOLE 1241 376 "
                    "718.856 718.856 607.19 185.22' --structure tracks --out poses.txt\n"
                    "  planarloc localize --map kitti.db --sequence frames.txt --odometry odom.txt --out poses.txt"
                    "   # a stream: pose, covariance and status (localized/predicted/lost) per frame")
    p.add_argument("--map", required=True, type=Path, help="map file from `planarloc map build`")
    p.add_argument("images", nargs="+", type=Path, help="query image files or folders of images")
    p.add_argument("--camera", help="query intrinsics 'MODEL W H PARAMS...' (COLMAP syntax); default: the map's "
                                    "camera if the map has one camera of the same image size")
    p.add_argument("--out", "-o", type=Path, default=Path("poses.txt"), help="results file (default: %(default)s)")
    p.add_argument("--json-dir", type=Path, help="folder for one JSON per query (default: <out>.json.d)")
    add_localizer_args(p)
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
    return out


def _default_camera(loc: Localizer, shape: tuple[int, int]) -> Camera:
    cams = {(p.camera.model, p.camera.width, p.camera.height, p.camera.params) for p in loc.db.posed_images()}
    if len(cams) != 1:
        raise ValueError("the map has several cameras: pass the query intrinsics with --camera")
    cam = Camera(*next(iter(cams)))
    if (cam.height, cam.width) != shape:
        raise ValueError(f"query images are {shape[1]}x{shape[0]} but the map camera is {cam.width}x{cam.height}: "
                         "pass --camera")
    return cam


def run(args: argparse.Namespace) -> int:
    if args.sequence:
        return localize_sequence(args)
    if args.odometry:
        raise ValueError("--odometry: only used with --sequence")
    queries = _collect(args.images)
    loc = Localizer(args.map, localizer_config(args))
    pairs = read_hloc_pairs(args.pairs) if args.pairs else None
    json_dir = args.json_dir or args.out.with_name(args.out.name + ".json.d")
    json_dir.mkdir(parents=True, exist_ok=True)
    camera = parse_camera(args.camera) if args.camera else None
    poses, failed = [], 0
    with progress_bar() as update:
        for i, (name, path) in enumerate(queries):
            image = read_gray(path)
            cam = camera or _default_camera(loc, image.shape[:2])
            refs = retrieve_from_pairs(pairs, name, loc.config.top_n) if pairs else None
            est = loc.localize(image, cam, refs)
            record = {"name": name, **est.to_dict()}
            (json_dir / (name.replace("/", "__") + ".json")).write_text(json.dumps(record, indent=1))
            if est.success:
                poses.append((name, est.pose))
            else:
                failed += 1
            update("localize", i + 1, len(queries))
    write_pose_list(args.out, poses)
    console.print(f"localized {len(poses)} of {len(queries)} queries ({failed} failed) -> {args.out}, "
                  f"details in {json_dir}/")
    return 0
