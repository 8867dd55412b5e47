"""`planarloc map build|info`: create maps from posed images."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from planarloc.cli.options import add_dataset_args, add_feature_args, feature_config
from planarloc.cli.progress import console, progress_bar
from planarloc.io.datasets import read_dataset
from planarloc.pipeline.map_builder import build_map
from planarloc.pipeline.map_database import MapDatabase


def parse_dataset_options(items: list[str] | None) -> dict:
    """KEY=VALUE pairs -> dict with JSON-decoded values where possible (numbers, true/false)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--dataset-option {item!r}: expected KEY=VALUE, e.g. tum_camera=fr1")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="build or inspect a map (a SQLite file of posed images and their features)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="A map is just posed images with their features: no 3D model is built.\n\n"
                                   "examples:\n  planarloc map build data/kitti_seq2 --format kitti --out kitti.db\n"
                                   "  planarloc map info kitti.db")
    msub = p.add_subparsers(dest="map_command", required=True)
    b = msub.add_parser(
        "build", help="build (or resume / extend) a map from a dataset",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Extract RootSIFT features of every posed image and store them with the poses in MAP.db, "
                    "then index the map for retrieval (VLAD).\n\n"
                    "Re-running the same command resumes an interrupted build; running it on another "
                    "dataset with the same --out appends those images.\n\n"
                    "example:\n  planarloc map build data/kitti_seq2 --format kitti --every 2 --out kitti.db")
    add_dataset_args(b)
    b.add_argument("--every", type=int, default=1, help="only frames with index %% N == 0 go into the map (default: 1)")
    b.add_argument("--out", "-o", required=True, type=Path, help="map file to create or extend")
    b.add_argument("--dataset-option", action="append", metavar="KEY=VALUE",
                   help="importer option, e.g. tum_camera=fr1 or max_dt=0.05 (repeatable)")
    add_feature_args(b)
    b.set_defaults(func=run_build)
    i = msub.add_parser("info", help="summarise a map", formatter_class=argparse.RawDescriptionHelpFormatter,
                        description="Print the number of images, the feature configuration and whether the build "
                                    "is complete.\n\nexample:\n  planarloc map info kitti.db")
    i.add_argument("map", type=Path)
    i.set_defaults(func=run_info)


def run_build(args: argparse.Namespace) -> int:
    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    images = read_dataset(args.dataset, args.format, **parse_dataset_options(args.dataset_option))
    images = [im for im in images if im.index % args.every == 0]
    console.print(f"building map [bold]{args.out}[/] from {len(images)} images of {args.dataset}")
    with progress_bar() as update:
        build_map(images, args.out, feature_config(args), num_words=args.vocabulary_size, progress=update)
    return run_info(argparse.Namespace(map=args.out))


def run_info(args: argparse.Namespace) -> int:
    with MapDatabase.open(args.map) as db:
        n = db.num_images()
        cfg = db.config
        console.print(f"{args.map}: {n} images, features {cfg.get('feature_name', '?')}, "
                      f"{'complete' if db.is_complete else '[yellow]incomplete build[/]'}")
    return 0
