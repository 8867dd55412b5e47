"""The CPU side of a localization request: prepare the query, localize, build the per-query record.

Runs in a worker process of the service (:mod:`planarloc.serve.worker_pool`, entry point
:func:`worker_main`) or in a Ray Serve replica. Each process opens its maps once, read-only
(:func:`open_localizers`), and keeps them. A request is prepared and configured like a
`planarloc localize` query (:meth:`~planarloc.localize.localizer.Localizer.prepare`,
:func:`~planarloc.localize.localizer.localizer_config`) and answered with the record it writes
(:func:`planarloc.localize.records.query_record`), so a served pose equals the CLI's pose for the
same image, camera and seed. A frame of a session is run by the session's stream
(:class:`~planarloc.serve.sessions.SessionStates`) in the worker that holds it.

Errors are sorted here (:func:`~planarloc.serve.requests.classify_error`): the request's are
:class:`~planarloc.serve.requests.RequestError` (4xx), the server's
:class:`~planarloc.serve.requests.ServerFault` (500, its detail logged by the worker).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path

from planarloc.compile import steps_for
from planarloc.compile.first_use import FirstUse, compile_setting, first_use_in_pool
from planarloc.features import learned
from planarloc.localize.localizer import Localizer
from planarloc.localize.records import query_record
from planarloc.serve.map_watch import MapFingerprint, fingerprint_change, map_fingerprint
from planarloc.serve.requests import LocalizeRequest, RequestError, ServerFault, classify_error
from planarloc.serve.sessions import SessionStates

logger = logging.getLogger(__name__)

_LOCALIZERS: dict[str, Localizer] = {}
_SESSIONS = SessionStates()
#: Maps this worker opened in another version than the server's (name -> change).
_CHANGED: dict[str, str] = {}


def _exit_with_parent(parent: int, period_s: float = 1.0) -> None:
    """Exit this worker when its server process is gone (e.g. SIGKILLed), never outlive it."""
    while os.getppid() == parent:
        time.sleep(period_s)
    os._exit(0)


def open_localizers(
    maps: Mapping[str, str | Path], expected: Mapping[str, MapFingerprint] | None = None
) -> dict[str, str]:
    """Open every map read-only (once per process; kept for the process' life).

    Args:
        maps: ``{name: path}``.
        expected: the server's fingerprints of the maps; a map whose file is not that version
            before or after it is opened is refused by this worker (returned).

    Returns:
        ``{name: change}`` of the maps that are not the expected version (empty when all are).
    """
    _LOCALIZERS.clear()
    _CHANGED.clear()
    for name, path in maps.items():
        before = map_fingerprint(path)
        _LOCALIZERS[name] = Localizer(Path(path))
        learned.load_backend(
            _LOCALIZERS[name].features.kind
        )  # a learned map's models load now, not in a request
        after = map_fingerprint(path)
        if expected is not None and name in expected:
            change = fingerprint_change(expected[name], before) or fingerprint_change(expected[name], after)
            if change is not None:
                _CHANGED[name] = change
    return dict(_CHANGED)


def start_kernels(localizers: list[Localizer]) -> FirstUse | None:
    """Before a process' first request: on an empty kernel cache, the kernels these maps'
    localizations need compile once for the whole pool (:func:`first_use_in_pool`), as Python
    meanwhile, or first with ``PLANARLOC_COMPILE=wait``. Poll the returned :class:`FirstUse`
    between requests (:func:`compiled_now`)."""
    steps = steps_for([loc.config for loc in localizers])
    return first_use_in_pool(steps, logger.warning, wait=compile_setting() == "wait")


def compiled_now(first: FirstUse | None) -> None:
    """Between requests: back to compiled kernels once the shared compile has ended (said once)."""
    if first is not None and first.poll():
        logger.warning("planarloc's kernels are compiled: requests run compiled from now on")


def localize_with(base: Localizer, req: LocalizeRequest) -> dict:
    """Localize one request with an open map; returns the per-query record (JSON-serialisable).

    Raises:
        RequestError: an undecodable image, a camera that does not fit it, invalid options (4xx).
        ServerFault: anything that goes wrong once the query is accepted (a damaged map, a bug).
    """
    try:
        loc = base.with_config(req.settings.config())
        query = loc.prepare(req.image, req.camera, name=req.name, gravity=req.gravity)
    except Exception as exc:  # noqa: BLE001 - sorted into the client's and the server's
        raise classify_error(exc, req.name) from None
    try:
        estimate = loc.localize_query(query)
    except Exception as exc:  # noqa: BLE001 - the query was accepted: whatever fails now is the server's
        error = classify_error(exc, req.name)
        raise (
            error
            if isinstance(error, ServerFault)
            else ServerFault(
                f"internal error ({type(exc).__name__}, logged on the server)", f"{req.name}: {exc}"
            )
        ) from None
    return query_record(req.name, estimate, query.gravity)


def _localizer(name: str) -> Localizer:
    if name not in _LOCALIZERS:
        raise RequestError(404, f"map: {name!r} is not open in this worker")
    if name in _CHANGED:
        raise RequestError(
            503,
            f"map {name!r}: this worker opened another version of it than the server serves",
            retry_after_s=1,
        )
    return _LOCALIZERS[name]


def localize_request(req: LocalizeRequest) -> dict:
    """Worker-process entry point: localize against the map opened by :func:`open_localizers`."""
    return localize_with(_localizer(req.map_name), req)


def session_frame_with(loc: Localizer, states: SessionStates, req: LocalizeRequest, generation: int) -> dict:
    """One frame of a session with an open map: the query checked like a single one, then the
    session's stream (:meth:`~planarloc.serve.sessions.SessionStates.step`)."""
    try:
        query = loc.prepare(req.image, req.camera, name=req.name, gravity=req.gravity)
    except Exception as exc:  # noqa: BLE001 - sorted into the client's and the server's
        raise classify_error(exc, req.name) from None
    return states.step(loc, dataclasses.replace(req, image=query.image, camera=query.camera), generation)


def session_frame(req: LocalizeRequest, generation: int) -> dict:
    """Worker-process entry point: one frame of a session held by this worker."""
    return session_frame_with(_localizer(req.map_name), _SESSIONS, req, generation)


def drop_sessions(ids: list[str]) -> int:
    """Worker-process entry point: free the streams of forgotten sessions; returns how many are left."""
    _SESSIONS.drop(ids)
    return len(_SESSIONS)


def ping() -> int:
    """Returns the worker's process id."""
    return os.getpid()


def _describe(exc: BaseException) -> tuple:
    """An exception as a message the server can always unpickle."""
    if isinstance(exc, RequestError):
        return ("request", exc.status, exc.message, exc.retry_after_s)
    fault = classify_error(exc)
    detail = fault.detail if isinstance(fault, ServerFault) else ""
    logger.error("request failed in worker %d: %s", os.getpid(), detail or fault, exc_info=exc)
    if isinstance(fault, RequestError):
        return ("request", fault.status, fault.message, fault.retry_after_s)
    return ("fault", fault.public)


def worker_main(conn, maps: Mapping[str, str], expected: Mapping[str, MapFingerprint]) -> None:
    """A worker process: open the maps, say ``("ready", pid, changed, compiling)``, then answer jobs.

    ``compiling``: the shared compile (:class:`~planarloc.compile.background.BackgroundCompile`)
    during which this worker runs its kernels as Python; None when they run compiled.

    Each job is ``(fn, args)``; the answer ``("ok", result)``, ``("request", status, message,
    retry_after)`` or ``("fault", public message)``. Ends when the server closes the pipe, or when
    the server process is gone.
    """
    logging.basicConfig(
        level=logging.WARNING, format="%(levelname)s %(name)s [worker %(process)d]: %(message)s"
    )
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    try:
        changed = open_localizers(maps, expected)
    except Exception as exc:  # noqa: BLE001 - reported to the server, which refuses to start
        logger.error("cannot open the maps: %s", exc)
        conn.send(("failed", f"{type(exc).__name__}: {' '.join(str(exc).split())}"))
        return
    try:
        first = start_kernels(list(_LOCALIZERS.values()))
    except Exception as exc:  # noqa: BLE001 - not fatal: the kernels compile on first use, as before
        logger.warning("cannot check the kernel cache (%s): kernels compile where first called", exc)
        first = None
    # The server reports workers that run as Python (/healthz, /metrics) while this compile runs.
    compiling = first.compiling.seen_from_elsewhere() if first is not None and first.as_python else None
    conn.send(("ready", os.getpid(), changed, compiling))
    while True:
        try:
            fn, args = conn.recv()
        except (EOFError, OSError):
            return
        compiled_now(first)
        try:
            answer: tuple = ("ok", fn(*args))
        except Exception as exc:  # noqa: BLE001 - every failure is answered
            answer = _describe(exc)
        try:
            conn.send(answer)
        except (EOFError, OSError):
            return
        except Exception as exc:  # noqa: BLE001 - an unpicklable result is a bug: answered as a fault
            conn.send(_describe(exc))
