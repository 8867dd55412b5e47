"""`planarloc serve`: the localization service over HTTP (FastAPI + uvicorn)."""

from __future__ import annotations

import argparse
import asyncio
import errno
import ipaddress
import logging
import math
import socket
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import note
from planarloc.cli.options import add_map_features_arg, add_number, check_map_file_features
from planarloc.compile.first_use import compile_setting
from planarloc.serve.settings import (
    DEFAULT_BODY_TIMEOUT_S,
    DEFAULT_HEADER_TIMEOUT_S,
    DEFAULT_JOB_TIMEOUT_S,
    DEFAULT_MAX_IMAGE_BYTES,
    DEFAULT_MAX_SESSIONS,
    DEFAULT_QUEUE,
    DEFAULT_QUEUE_TIMEOUT_S,
    DEFAULT_SESSION_IDLE_S,
    DEFAULT_WORKERS,
)

logger = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "serve",
        "serve localization over HTTP for a fleet of robots",
        """POST /v1/localize (multipart: image, and optionally camera 'MODEL W H PARAMS...' (default: the
        map's camera), map, gravity 'gx gy gz', method, structure, seed) answers the record `planarloc
        localize` writes per query; with session=ROBOT_ID, stamp=SECONDS and optionally odometry='tx ty tz qx
        qy qz qw' it is a frame of that robot's stream and answers the record of `planarloc localize
        --sequence` (status localized/predicted/lost, covariance). GET /v1/maps, /healthz, /metrics
        (Prometheus). Localization runs in --workers processes that open every map once, read-only; a
        request is admitted once its body has arrived, at most --workers + --queue at a time, the others get
        503 with Retry-After. A map file changed on disk is refused until restart. The banner on stderr
        names the address bound (with --port 0: the port chosen) once the workers are ready. On an empty
        kernel cache (no `planarloc warmup`) the workers share one background compile and answer as
        Python (slower) until it ends; PLANARLOC_COMPILE=wait compiles first, before the banner. Ctrl-C
        stops it. Needs: pip install 'planarloc[serve]'.""",
        [
            "planarloc serve --map office=office.db --map lab=lab.db --workers 2 --port 8080",
            "curl -F image=@q.png -F 'camera=PINHOLE 640 480 525 525 320 240' -F map=office "
            "http://127.0.0.1:8080/v1/localize",
        ],
        run,
    )
    p.add_argument(
        "--map",
        dest="maps",
        action="append",
        required=True,
        metavar="PATH|NAME=PATH",
        help="map file to serve, named after its file stem or NAME (repeatable)",
    )
    add_map_features_arg(p)
    p.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default: %(default)s, loopback only)"
    )
    p.add_argument(
        "--port",
        type=int,
        default=8080,
        help="TCP port, 0 = any free port (the banner on stderr names the port bound; default: %(default)s)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=DEFAULT_WORKERS,
        help="localization worker processes (default: %(default)s)",
    )
    p.add_argument(
        "--queue",
        type=int,
        default=DEFAULT_QUEUE,
        help="requests waiting for a worker before 503 (default: %(default)s)",
    )
    token = p.add_mutually_exclusive_group()
    token.add_argument(
        "--token",
        help="require 'Authorization: Bearer TOKEN' on /v1/* and /metrics (visible in "
        "the process list: prefer --token-file or $PLANARLOC_TOKEN)",
    )
    token.add_argument(
        "--token-file",
        type=Path,
        metavar="FILE",
        help="read the token from the first line of FILE (default: $PLANARLOC_TOKEN if set)",
    )
    p.add_argument(
        "--max-image-mb",
        type=float,
        default=DEFAULT_MAX_IMAGE_BYTES / (1024 * 1024),
        help="image upload limit in MB, for every transfer encoding (default: %(default)s)",
    )
    _add_limit_args(p)


def _add_limit_args(p: argparse.ArgumentParser) -> None:
    """The service's time limits and its number of sessions."""
    limits = p.add_argument_group("limits (seconds unless stated)")
    for option, default, text in (
        ("--header-timeout", DEFAULT_HEADER_TIMEOUT_S, "time for a request's headers once connected"),
        (
            "--body-timeout",
            DEFAULT_BODY_TIMEOUT_S,
            "time for a request's body (408 beyond; slow clients hold no worker or queue place meanwhile)",
        ),
        (
            "--queue-timeout",
            DEFAULT_QUEUE_TIMEOUT_S,
            "longest wait of an admitted request for a worker (503 beyond)",
        ),
        (
            "--job-timeout",
            DEFAULT_JOB_TIMEOUT_S,
            "longest localization; beyond it the worker is replaced (503)",
        ),
        ("--session-idle", DEFAULT_SESSION_IDLE_S, "a session without a frame for this long is evicted"),
    ):
        add_number(limits, option, float, default, text)
    limits.add_argument(
        "--max-sessions",
        type=int,
        default=DEFAULT_MAX_SESSIONS,
        help="robot sessions kept at once; a new one evicts the least recently used idle one "
        "(default: %(default)s)",
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
            raise ValueError(
                f"--port {port}: {host}:{port} is already in use (another server?); choose another "
                "port, or --port 0 for any free one"
            ) from None
        raise ValueError(f"--host {host} --port {port}: cannot listen there ({exc.strerror})") from None
    return sock


def check_settings(args: argparse.Namespace) -> None:
    """Every numeric option, before anything starts."""
    if not 0 <= args.port < 65536:
        raise ValueError(f"--port: expected 0..65535, got {args.port}")
    if not args.max_image_mb > 0 or not math.isfinite(args.max_image_mb):
        raise ValueError(f"--max-image-mb: must be a positive number, got {args.max_image_mb}")
    if args.workers < 1 or args.queue < 0:
        raise ValueError(f"--workers must be >= 1 and --queue >= 0, got {args.workers} and {args.queue}")
    if args.max_sessions < 1:
        raise ValueError(f"--max-sessions: must be >= 1, got {args.max_sessions}")
    compile_setting()  # $PLANARLOC_COMPILE: a bad value is one line here, not a worker failing to start
    for option in ("header_timeout", "body_timeout", "queue_timeout", "job_timeout", "session_idle"):
        value = getattr(args, option)
        if not value > 0 or not math.isfinite(value):
            raise ValueError(
                f"--{option.replace('_', '-')}: must be a positive number of seconds, got {value}"
            )


def run(args: argparse.Namespace) -> int:
    from planarloc.client import resolve_token
    from planarloc.extras import require
    from planarloc.serve.app import ServeSettings, create_app, header_timeout_protocol
    from planarloc.serve.requests import MapSet

    uvicorn = require("uvicorn", "serve")
    check_settings(args)
    token = resolve_token(args.token, args.token_file)
    try:
        loopback = ipaddress.ip_address(args.host).is_loopback
    except ValueError:
        loopback = args.host == "localhost"
    if not loopback and not token:
        logger.warning("serving on %s without a token: anyone who can reach it can use it", args.host)
    maps = MapSet.from_specs(args.maps)
    for path in maps.paths.values():  # --features: every served map must have that type
        check_map_file_features(path, args.features)
    settings = ServeSettings(
        maps,
        workers=args.workers,
        queue_size=args.queue,
        token=token,
        max_image_bytes=int(args.max_image_mb * 1024 * 1024),
        header_timeout_s=args.header_timeout,
        body_timeout_s=args.body_timeout,
        queue_timeout_s=args.queue_timeout,
        job_timeout_s=args.job_timeout,
        max_sessions=args.max_sessions,
        session_idle_s=args.session_idle,
    )
    sock = bind(args.host, args.port)  # before the workers start: a busy port fails at once
    port = sock.getsockname()[1]
    host = f"[{args.host}]" if ":" in args.host else args.host
    try:
        app = create_app(settings)
        service = app.state.service
        config = uvicorn.Config(
            app,
            log_level="warning",
            timeout_graceful_shutdown=5,
            http=header_timeout_protocol(settings.header_timeout_s),
        )
        server = uvicorn.Server(config)

        async def serve() -> None:
            await service.start()  # workers up and maps open before the banner: failures are one line
            try:
                note(
                    f"serving {', '.join(settings.maps.paths)} on http://{host}:{port} "
                    f"({settings.workers} workers, queue {settings.queue_size})"
                )
                await server.serve(sockets=[sock])
            finally:
                await service.close()

        asyncio.run(serve())
    finally:
        sock.close()
    return 0
