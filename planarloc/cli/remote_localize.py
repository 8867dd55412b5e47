"""`planarloc localize --server URL`: the queries of a `planarloc localize` run, localized by a
running `planarloc serve` instead of in this process.

The run is the same as a local one (:mod:`planarloc.cli.localize_command`): the same queries and
names, the same results and records written by the same writer, the same exit codes. A query the
server refuses as bad input (4xx: an undecodable image, a camera that does not fit) is recorded
as not processed with the server's reason and the run goes on (exit code 3); a server that cannot
be reached, refuses the token or fails (5xx after the client's retries) stops the run (exit 1,
the results file is left as it was).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from pathlib import Path

from planarloc.cli.query_sources import QuerySource
from planarloc.geometry.camera import Camera
from planarloc.localize.localizer import LocalizerConfig
from planarloc.localize.records import error_record

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
#: Answers that are about one query (recorded, the run goes on), not about the server or the run.
_QUERY_ERRORS = {400, 413, 415, 422}


def add_server_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("remote (planarloc serve)")
    g.add_argument(
        "--server",
        metavar="URL",
        help="localize through this planarloc service (e.g. http://127.0.0.1:8080); --map is then "
        "the served map's name; example: planarloc localize --server http://127.0.0.1:8080 --map office "
        "q/*.png --camera 'PINHOLE 640 480 525 525 320 240'",
    )
    token = g.add_mutually_exclusive_group()
    token.add_argument(
        "--token",
        help="bearer token of the service (visible in the process list: prefer "
        "--token-file or $PLANARLOC_TOKEN)",
    )
    token.add_argument(
        "--token-file",
        type=Path,
        metavar="FILE",
        help="read the service's token from the first line of FILE (default: $PLANARLOC_TOKEN)",
    )


def check_remote_args(args: argparse.Namespace) -> None:
    """Refuse, before any work, the options a server cannot take per request."""
    changed = [
        k.replace("_", "-") for k, default in _LOCAL_ONLY.items() if getattr(args, k, default) != default
    ]
    if changed:
        raise ValueError(
            f"--server: --{', --'.join(changed)} cannot be set per request (the server uses its "
            "defaults); drop them or localize locally"
        )


def remote_localizer(
    client, args: argparse.Namespace, camera: Camera | None, gravity: Iterable[float] | None
) -> Callable[[QuerySource], dict]:
    """``localize(query) -> record`` through ``client`` (a :class:`planarloc.client.Client`),
    after checking that the served map exists and, without ``camera``, has exactly one camera."""
    from planarloc.client import ServiceError

    map_name = str(args.map)
    try:
        maps = {m["name"]: m for m in client.maps()}
    except ServiceError as exc:
        raise ValueError(f"--server {args.server}: {exc}") from None
    if map_name not in maps:
        raise ValueError(
            f"--map {map_name}: the server serves no such map (it serves {', '.join(sorted(maps))})"
        )
    cameras = maps[map_name].get("cameras", [])
    if camera is None and len(cameras) != 1:
        raise ValueError(
            f"--server: map {map_name!r} has {len(cameras)} cameras: pass the query intrinsics with --camera"
        )
    g = None if gravity is None else tuple(float(v) for v in gravity)

    def localize(q: QuerySource) -> dict:
        try:
            data = q.path.read_bytes()
        except OSError as exc:
            return error_record(q.name, f"{q.path}: {exc.strerror or exc}", stamp=q.timestamp)
        try:
            record = client.localize(
                data,
                camera or q.camera,
                map=map_name,
                name=q.name.replace("/", "__"),
                method=args.method,
                structure=args.structure,
                seed=args.seed,
                gravity=g,
            )
        except ServiceError as exc:
            if exc.status in _QUERY_ERRORS:
                return error_record(q.name, f"{q.path}: the server answered {exc}", stamp=q.timestamp)
            raise ValueError(f"{q.path}: {args.server} answered {exc}") from None
        # the server knows neither the query's own name (it is sent flattened) nor its time
        return {**record, "name": q.name, "stamp": q.timestamp}

    return localize
