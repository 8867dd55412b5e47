"""`evaluate` inputs: one dataset split by ``--map-every``, or cross-session — map datasets plus
``--queries QUERY_DATASET`` in its own format (the paper's OpenLORIS protocol, Sec. V-B)."""

from __future__ import annotations

import argparse
from pathlib import Path

from planarloc.cli.options import parse_dataset_options
from planarloc.evaluation.queries import default_map_path, split_map_queries
from planarloc.io.datasets import FORMATS, read_dataset
from planarloc.io.sessions import read_sessions, session_labels, sessions_map_path
from planarloc.map.posed_image import PosedImage


def add_cross_session_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--map-every",
        type=int,
        help="one dataset: frames with index %% N == 0 form the map, the rest are queries",
    )
    p.add_argument(
        "--queries",
        metavar="QUERY_DATASET",
        help="cross-session: localize this dataset against a map of all the (map) datasets",
    )
    p.add_argument(
        "--queries-format", choices=sorted(FORMATS), help="format of --queries (default: --format)"
    )
    p.add_argument(
        "--queries-option",
        action="append",
        metavar="KEY=VALUE",
        help="importer option of --queries (repeatable; --dataset-option applies to the map datasets)",
    )


def read_map_and_queries(
    args: argparse.Namespace, features_name: str, settings: str = ""
) -> tuple[list[PosedImage], list[PosedImage], Path, dict, str]:
    """Map images, queries, map path, extra JSON fields and a title, for both protocols
    (``settings``: the map settings that key the cached map, with the map images' content)."""
    map_options = parse_dataset_options(args.dataset_option, fmt=args.format)
    if (args.queries is None) == (args.map_every is None):
        raise ValueError(
            "give either --map-every N (split one dataset) or --queries QUERY_DATASET (cross-session)"
        )
    if args.queries is None:
        if len(args.dataset) != 1:
            raise ValueError(
                f"--map-every splits one dataset, got {len(args.dataset)}; use --queries for several"
            )
        images = read_dataset(args.dataset[0], args.format, **map_options)
        map_images, queries = split_map_queries(images, args.map_every)
        map_path = args.map or default_map_path(
            Path(args.dataset[0]), args.map_every, features_name, map_images, settings=settings
        )
        return (
            map_images,
            queries,
            map_path,
            {"dataset": str(args.dataset[0]), "map_every": args.map_every},
            f"{Path(args.dataset[0]).name}, map every {args.map_every}",
        )
    map_images = read_sessions(args.dataset, args.format, **map_options)
    queries = read_dataset(
        Path(args.queries),
        args.queries_format or args.format,
        **parse_dataset_options(args.queries_option, "--queries-option", args.queries_format or args.format),
    )
    map_path = args.map or sessions_map_path(
        args.dataset, args.format, map_options, f"{features_name}|{settings}"
    )
    extra = {
        "map_datasets": [str(d) for d in args.dataset],
        "map_format": args.format,
        "queries_dataset": str(args.queries),
        "queries_format": args.queries_format or args.format,
    }
    return (
        map_images,
        queries,
        map_path,
        extra,
        f"map {'+'.join(session_labels(args.dataset))}, queries {Path(args.queries).name}",
    )
