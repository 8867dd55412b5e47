"""`planarloc localize --server URL`: localize image files through a running `planarloc serve`.

Writes the same outputs as a local run (pose list and one JSON record per query), from the
records the server returns.
"""

from __future__ import annotations

import argparse
import json

from planarloc.cli.options import parse_gravity
from planarloc.cli.progress import console, progress_bar
from planarloc.geometry.pose import Pose
from planarloc.io.lines import write_text_atomic
from planarloc.localize.localizer import LocalizerConfig
from planarloc.localize.records import query_record_filename

_LOC = LocalizerConfig()
#: Options the service takes per request; the others are the server's and cannot be changed remotely.
_LOCAL_ONLY = {
    "pairs": None,
    "use_depth": False,
    "iterations": None,
    "top_n": _LOC.top_n,
    "threshold": _LOC.ransac.threshold_px,
    "max_position_std": _LOC.ransac.max_position_std_m,
    "gravity_file": None,
    "tum": None,
    "plot_matches": None,
    "rerun": None,
}


def add_server_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("remote (planarloc serve)")
    g.add_argument(
        "--server",
        metavar="URL",
        help="localize through this planarloc service (e.g. http://127.0.0.1:8080); --map is then "
        "the served map's name; example: planarloc localize --server http://127.0.0.1:8080 --map office "
        "q/*.png --camera 'PINHOLE 640 480 525 525 320 240'",
    )
    g.add_argument("--token", help="bearer token of the service (planarloc serve --token)")


def _served_camera(client, map_name: str) -> str:
    """The camera of a served map that has exactly one (like the local default), else an error."""
    from planarloc.client import ServiceError

    try:
        maps = {m["name"]: m for m in client.maps()}
    except ServiceError as exc:
        raise ValueError(f"--server: {exc}") from None
    cameras = maps.get(map_name, {}).get("cameras", [])
    if len(cameras) != 1:
        raise ValueError(
            f"--server: map {map_name!r} has {len(cameras)} cameras: pass the query intrinsics with --camera"
        )
    return cameras[0]


def run_remote(args: argparse.Namespace, queries: list[tuple[str, object]]) -> int:
    """Send every query to ``args.server``; same result files as the local run."""
    from planarloc.client import Client, ServiceError

    changed = [
        k.replace("_", "-") for k, default in _LOCAL_ONLY.items() if getattr(args, k, default) != default
    ]
    if changed:
        raise ValueError(
            f"--server: --{', --'.join(changed)} cannot be set per request (the server uses its "
            "defaults); drop them or localize locally"
        )
    json_dir = args.json_dir or args.out.with_name(args.out.name + ".json.d")
    json_dir.mkdir(parents=True, exist_ok=True)
    poses, failed = [], 0
    with Client(args.server, token=args.token) as client, progress_bar() as update:
        camera = args.camera or _served_camera(client, str(args.map))
        gravity = tuple(float(v) for v in parse_gravity(args.gravity)) if getattr(args, "gravity", None) else None
        for i, (name, path) in enumerate(queries):
            try:
                record = client.localize(
                    path,
                    camera,
                    map=str(args.map),
                    name=name.replace("/", "__"),
                    method=args.method,
                    structure=args.structure,
                    seed=args.seed,
                    gravity=gravity,
                )
            except ServiceError as exc:
                raise ValueError(f"{path}: {args.server} answered {exc}") from None
            record["name"] = name
            (json_dir / query_record_filename(name)).write_text(json.dumps(record, indent=1))
            if record["success"]:
                Pose.from_quat_wxyz(record["quat_wxyz"], record["t"])  # validates the server's answer
                # The record's own numbers, not a quaternion -> matrix -> quaternion round trip, so the
                # file is byte-identical to a local run's.
                poses.append(
                    " ".join([name, *(repr(float(v)) for v in (*record["quat_wxyz"], *record["t"]))]) + "\n"
                )
            else:
                failed += 1
            update("localize", i + 1, len(queries))
    write_text_atomic(args.out, poses)
    console.print(
        f"localized {len(poses)} of {len(queries)} queries ({failed} failed) via {args.server} -> "
        f"{args.out}, details in {json_dir}/"
    )
    return 0
