"""The CPU side of a localization request: decode the image, localize, build the per-query record.

Runs in a worker process of the service (:mod:`planarloc.serve.worker_pool`) or in a Ray Serve
replica. Each process opens its maps once, read-only (:func:`open_localizers`), and keeps them.
The record is :func:`planarloc.localize.records.query_record`, the one ``planarloc localize``
writes, and the configuration is built by the CLI's own option parser, so a served pose
equals the CLI's pose for the same image, camera and seed.
"""

from __future__ import annotations

import argparse
import copy
import functools
import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.localize.records import query_record
from planarloc.serve.requests import LocalizeRequest, RequestError

logger = logging.getLogger(__name__)

_LOCALIZERS: dict[str, Localizer] = {}


def _exit_with_parent(parent: int, period_s: float = 1.0) -> None:
    """Exit this worker when its server process is gone (e.g. SIGKILLed), never outlive it."""
    while os.getppid() == parent:
        time.sleep(period_s)
    os._exit(0)


def open_localizers(maps: Mapping[str, str | Path]) -> dict[str, Localizer]:
    """Open every map read-only (process initializer of the workers); kept for the process' life.

    Also starts a watcher that ends the worker when the server process dies.
    """
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    _LOCALIZERS.clear()
    for name, path in maps.items():
        _LOCALIZERS[name] = Localizer(Path(path))
    return _LOCALIZERS


@functools.cache
def _cli_localizer_parser() -> argparse.ArgumentParser:
    from planarloc.cli.options import add_localizer_args

    parser = argparse.ArgumentParser(add_help=False)
    add_localizer_args(parser)
    return parser


def request_config(req: LocalizeRequest) -> LocalizerConfig:
    """The configuration `planarloc localize` builds for ``--method M --structure S --seed N``.

    Built by the CLI's own option parser and ``localizer_config``, so every other setting has the
    CLI's default by construction (a served pose equals the CLI's for the same input and seed).
    """
    from planarloc.cli.options import localizer_config

    argv = []
    for option, value in (("--method", req.method), ("--structure", req.structure), ("--seed", req.seed)):
        if value is not None:
            argv += [option, str(value)]
    return localizer_config(_cli_localizer_parser().parse_args(argv))


def decode_gray(req: LocalizeRequest) -> np.ndarray:
    """The request's image as (H, W) uint8, decoded like ``cv2.imread(..., IMREAD_GRAYSCALE)``."""
    image = cv2.imdecode(np.frombuffer(req.image, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise RequestError(400, "image: cannot decode (corrupt or truncated JPEG/PNG)")
    if (image.shape[1], image.shape[0]) != (req.camera.width, req.camera.height):
        raise RequestError(
            400,
            f"camera: {req.camera.width}x{req.camera.height} does not fit the "
            f"{image.shape[1]}x{image.shape[0]} image",
        )
    return image


def localize_with(base: Localizer, req: LocalizeRequest) -> dict:
    """Localize one request with an open map; returns the per-query record (JSON-serialisable).

    Raises:
        RequestError: undecodable image, invalid options.
    """
    image = decode_gray(req)
    try:
        loc = copy.copy(base)  # shares the open map, index and caches; only the configuration differs
        loc.config = request_config(req)
    except ValueError as exc:
        raise RequestError(400, str(exc)) from None
    gravity = None if req.gravity is None else np.asarray(req.gravity, dtype=float)
    est = loc.localize(image, req.camera, gravity=gravity)
    return query_record(req.name, est, gravity)


def localize_request(req: LocalizeRequest) -> dict:
    """Worker-process entry point: localize against the map opened by :func:`open_localizers`."""
    if req.map_name not in _LOCALIZERS:
        raise RequestError(404, f"map: {req.map_name!r} is not open in this worker")
    return localize_with(_LOCALIZERS[req.map_name], req)


def ping() -> int:
    """Warm-up task: returns the worker's process id once its maps are open."""
    return os.getpid()
