"""The CPU side of a localization request: prepare the query, localize, build the per-query record.

Runs in a worker process of the service (:mod:`planarloc.serve.worker_pool`) or in a Ray Serve
replica. Each process opens its maps once, read-only (:func:`open_localizers`), and keeps them.
A request is prepared and configured like a `planarloc localize` query
(:meth:`~planarloc.localize.localizer.Localizer.prepare`,
:func:`~planarloc.localize.localizer.localizer_config`) and answered with the record it writes
(:func:`planarloc.localize.records.query_record`), so a served pose equals the CLI's pose for the
same image, camera and seed.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path

from planarloc.localize.localizer import Localizer, localizer_config
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


def localize_with(base: Localizer, req: LocalizeRequest) -> dict:
    """Localize one request with an open map; returns the per-query record (JSON-serialisable).

    Raises:
        InputError: an undecodable image, a camera that does not fit it, invalid options (the
            service answers 400).
    """
    loc = base.with_config(localizer_config(method=req.method, structure=req.structure, seed=req.seed))
    query = loc.prepare(req.image, req.camera, name=req.name, gravity=req.gravity)
    return query_record(req.name, loc.localize_query(query), query.gravity)


def localize_request(req: LocalizeRequest) -> dict:
    """Worker-process entry point: localize against the map opened by :func:`open_localizers`."""
    if req.map_name not in _LOCALIZERS:
        raise RequestError(404, f"map: {req.map_name!r} is not open in this worker")
    return localize_with(_LOCALIZERS[req.map_name], req)


def ping() -> int:
    """Warm-up task: returns the worker's process id once its maps are open."""
    return os.getpid()
