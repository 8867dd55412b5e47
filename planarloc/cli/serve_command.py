"""`planarloc serve`: the localization service over HTTP (FastAPI + uvicorn)."""

from __future__ import annotations

import argparse
import errno
import ipaddress
import logging
import socket

from planarloc.cli.commands import add_command
from planarloc.cli.console import note
from planarloc.serve.settings import DEFAULT_MAX_IMAGE_BYTES, DEFAULT_QUEUE, DEFAULT_WORKERS

logger = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "serve", "serve localization over HTTP for a fleet of robots",
        """POST /v1/localize (multipart: image, and optionally camera 'MODEL W H PARAMS...' (default: the
        map's camera), map, gravity 'gx gy gz', session, method, structure, seed) answers the record
        `planarloc localize` writes per query. GET /v1/maps, /healthz, /metrics (Prometheus). Localization
        runs in --workers processes that open every map once, read-only; at most --workers + --queue
        requests are admitted, the others get 503 with Retry-After. The banner on stderr names the address
        bound (with --port 0: the port chosen). Ctrl-C stops it. Needs: pip install 'planarloc[serve]'.""",
        ["planarloc serve --map office=office.db --map lab=lab.db --workers 2 --port 8080",
         "curl -F image=@q.png -F 'camera=PINHOLE 640 480 525 525 320 240' -F map=office "
         "http://127.0.0.1:8080/v1/localize"],
        run)
    p.add_argument(
        "--map",
        dest="maps",
        action="append",
        required=True,
        metavar="PATH|NAME=PATH",
        help="map file to serve, named after its file stem or NAME (repeatable)",
    )
    p.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default: %(default)s, loopback only)"
    )
    p.add_argument(
        "--port", type=int, default=8080,
        help="TCP port, 0 = any free port (the banner on stderr names the port bound; default: %(default)s)"
    )
    p.add_argument(
        "--workers", type=int, default=DEFAULT_WORKERS, help="localization worker processes (default: %(default)s)"
    )
    p.add_argument(
        "--queue", type=int, default=DEFAULT_QUEUE,
        help="requests waiting for a worker before 503 (default: %(default)s)"
    )
    p.add_argument("--token", help="require 'Authorization: Bearer TOKEN' on /v1/* and /metrics")
    p.add_argument(
        "--max-image-mb", type=float, default=DEFAULT_MAX_IMAGE_BYTES / (1024 * 1024),
        help="image upload limit in MB (default: %(default)s)"
    )


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (0: any free port), or one line saying why not."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise ValueError(f"--host {host}: cannot resolve it ({exc.strerror})") from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ValueError(f"--port {port}: {host}:{port} is already in use (another server?); choose another "
                             "port, or --port 0 for any free one") from None
        raise ValueError(f"--host {host} --port {port}: cannot listen there ({exc.strerror})") from None
    return sock


def run(args: argparse.Namespace) -> int:
    from planarloc.extras import require
    from planarloc.serve.app import ServeSettings, create_app
    from planarloc.serve.requests import MapSet

    uvicorn = require("uvicorn", "serve")
    if not 0 <= args.port < 65536:
        raise ValueError(f"--port: expected 0..65535, got {args.port}")
    if args.max_image_mb <= 0:
        raise ValueError(f"--max-image-mb: must be positive, got {args.max_image_mb}")
    if args.workers < 1 or args.queue < 0:
        raise ValueError(f"--workers must be >= 1 and --queue >= 0, got {args.workers} and {args.queue}")
    try:
        loopback = ipaddress.ip_address(args.host).is_loopback
    except ValueError:
        loopback = args.host == "localhost"
    if not loopback and not args.token:
        logger.warning("serving on %s without --token: anyone who can reach it can use it", args.host)
    settings = ServeSettings(
        MapSet.from_specs(args.maps),
        workers=args.workers,
        queue_size=args.queue,
        token=args.token,
        max_image_bytes=int(args.max_image_mb * 1024 * 1024),
    )
    sock = bind(args.host, args.port)  # before the workers start: a busy port fails at once
    port = sock.getsockname()[1]
    host = f"[{args.host}]" if ":" in args.host else args.host
    app = create_app(settings)
    note(f"serving {', '.join(settings.maps.paths)} on http://{host}:{port} "
         f"({settings.workers} workers, queue {settings.queue_size})")
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=5))
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
    return 0
