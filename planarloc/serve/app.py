"""The localization service: a FastAPI app over a :class:`~planarloc.serve.worker_pool.WorkerPool`.

Endpoints:

- ``POST /v1/localize`` — multipart form: ``image`` (JPEG/PNG file), and optionally ``camera``
  (``MODEL W H PARAMS...``; default: the map's, when it has one), ``map``, ``gravity``
  (``gx gy gz``), ``method``, ``structure``, ``seed``, and for a frame of a robot's stream
  ``session``, ``stamp`` and ``odometry`` (:mod:`planarloc.serve.sessions`). Answers the JSON
  ``planarloc localize`` writes per query (:func:`planarloc.localize.records.query_record`), or
  per frame for a session (:func:`planarloc.localize.records.frame_record`). A failed
  localization is a 200 with ``success: false`` and its status.
- ``GET /v1/maps`` — the served maps (name, images, cameras, complete, and ``status``: ``ok``, or
  what happened to the file since the server started).
- ``GET /healthz`` — the pool and the maps as they are now (no token needed): 200 ``ok`` or
  ``degraded`` (a worker down or restarting, a map refused), 503 ``failing`` (no worker alive, or
  no map servable). ``workers_as_python``: workers that answer as Python, slower, because the
  kernel cache was empty and the compile they share still runs (``ok`` all the same: the
  answers are the compiled kernels' poses).
- ``GET /metrics`` — Prometheus exposition (:class:`~planarloc.serve.metrics.ServiceMetrics`).

Answers other than 200 are ``{"error": "<one line>"}``: 4xx for the request's faults (400 bad
field, 404 unknown map, 408 body too slow, 409 a session frame out of order, 410 a session
that was evicted or lost, 413 over a limit, 415 not a multipart form / not a JPEG or PNG),
503 + ``Retry-After`` for load and for what a retry can fix (overload, a worker that died, a map
changed on disk), 500 for the server's faults (a damaged map, a bug: logged, the answer names no
path or internals). With a token, ``/v1/*`` and ``/metrics`` need ``Authorization: Bearer <token>``
(the scheme in any case, as RFC 7235 says: ``bearer``, ``BEARER``; the token exactly).

Order of a localize request: token → body read within ``body_timeout_s`` and the limits
(:mod:`planarloc.serve.form`) → map still the version the server started with
(:mod:`planarloc.serve.map_watch`) → admission (bounded) → worker → map checked again → answer.
"""

# No `from __future__ import annotations`: FastAPI reads the handlers' annotations at definition time.
import asyncio
import hmac
import logging
import os
import sys
import tempfile
import time
from collections.abc import Iterable
from contextlib import asynccontextmanager
from pathlib import Path

from planarloc.extras import require
from planarloc.io import strict_json
from planarloc.io.text import camera_text
from planarloc.map.store import MapDatabase
from planarloc.serve import worker
from planarloc.serve.form import FORM_OVERHEAD_BYTES, UploadBudget, read_localize_form
from planarloc.serve.map_watch import MapWatch
from planarloc.serve.metrics import ServiceMetrics
from planarloc.serve.requests import MapSet, RequestError, ServerFault
from planarloc.serve.sessions import SessionTable
from planarloc.serve.settings import ServeSettings
from planarloc.serve.worker_pool import Overloaded, QueueTimeout, WorkerDied, WorkerPool

logger = logging.getLogger(__name__)

ENDPOINTS = ("/v1/localize", "/v1/maps", "/healthz", "/metrics")
#: Statuses after which the rest of the request may still be on the wire: the connection is closed.
_CLOSE_AFTER = {400, 408, 413, 415}


def map_summaries(maps: MapSet) -> list[dict]:
    """Name, image count, cameras and completeness of each served map (never its path)."""
    out = []
    for name, path in maps.paths.items():
        with MapDatabase.open(path, mode="r") as db:
            cameras = sorted({camera_text(p.camera) for p in db.posed_images()})
            out.append(
                {
                    "name": name,
                    "images": db.num_images(),
                    "complete": bool(db.is_complete),
                    "cameras": cameras,
                }
            )
    return out


class PathScrubber:
    """Removes the server's paths (maps, their folders, working, temporary and home folders, the
    installation) from texts sent to clients."""

    def __init__(self, paths: Iterable[Path]) -> None:
        found: set[str] = set()
        for p in paths:
            for q in (Path(p), Path(p).resolve()):
                found |= {str(q), str(q.parent)}
        found |= {
            os.getcwd(),
            tempfile.gettempdir(),
            str(Path.home()),
            sys.prefix,
            str(Path(__file__).resolve().parents[1]),
        }
        self._paths = sorted((f for f in found if len(f) > 1), key=len, reverse=True)

    def __call__(self, text: str) -> str:
        for p in self._paths:
            text = text.replace(p, "<server path>")
        return text


def bearer_token_matches(authorization: str, token: str) -> bool:
    """Whether an ``Authorization`` header value carries ``token`` with the Bearer scheme.

    The scheme is case-insensitive and separated from the token by one or more spaces (RFC 7235,
    section 2.1; RFC 6750, section 2.1); the token is compared exactly, in constant time.
    """
    scheme, _, credentials = authorization.strip(" ").partition(" ")
    given = credentials.lstrip(" ")
    scheme_ok = scheme.lower() == "bearer"
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), token.encode("utf-8")) and scheme_ok


class Service:
    """The state of one server: worker pool, map watch, sessions, upload budget and metrics."""

    def __init__(self, settings: ServeSettings) -> None:
        self.settings = settings
        self.watch = MapWatch(settings.maps.paths)
        self.pool = WorkerPool(
            settings.maps.paths,
            settings.workers,
            settings.queue_size,
            queue_timeout_s=settings.queue_timeout_s,
            job_timeout_s=settings.job_timeout_s,
            expected=self.watch.original,
        )
        self.sessions = SessionTable(settings.workers, settings.max_sessions, settings.session_idle_s)
        self.pool.on_worker_lost = self._worker_lost
        self.pool.on_map_changed = self.watch.mark
        self.budget = UploadBudget(self.pool.capacity * (settings.max_image_bytes + FORM_OVERHEAD_BYTES))
        self.metrics = ServiceMetrics(self)
        self.summaries = map_summaries(settings.maps)
        self.scrub = PathScrubber(settings.maps.paths.values())
        self.started = False
        self._sweeper: asyncio.Task | None = None

    def _worker_lost(self, slot: int, reason: str) -> None:
        self.sessions.lose_slot(slot, reason)
        self.flush_drops()

    def flush_drops(self) -> None:
        """Tell the workers to free the streams of forgotten sessions."""
        by_slot: dict[int, list[str]] = {}
        for entry in self.sessions.take_drops():
            by_slot.setdefault(entry.slot, []).append(entry.id)
        for slot, ids in by_slot.items():
            self.pool.post(slot, worker.drop_sessions, ids)

    async def _sweep(self) -> None:
        period = min(5.0, self.settings.session_idle_s / 4)
        while True:
            await asyncio.sleep(period)
            self.sessions.evict_idle()
            self.flush_drops()
            self.watch.check_all()

    async def start(self) -> None:
        """Start the workers (raises ValueError with one line if they cannot open the maps)."""
        if self.started:
            return
        await self.pool.start()
        self._sweeper = asyncio.ensure_future(self._sweep())
        self.started = True
        logger.info("serving %s with %d workers", ", ".join(self.settings.maps.paths), self.pool.workers)

    async def close(self) -> None:
        if self._sweeper is not None:
            self._sweeper.cancel()
        await self.pool.close()
        self.started = False

    def health(self) -> tuple[dict, int]:
        alive = self.pool.alive()
        changes = self.watch.check_all()
        servable = [name for name, change in changes.items() if change is None]
        if sum(alive) == self.pool.workers and len(servable) == len(changes):
            status = "ok"
        elif sum(alive) == 0 or not servable:
            status = "failing"
        else:
            status = "degraded"
        body = {
            "status": status,
            "workers": self.pool.workers,
            "workers_alive": sum(alive),
            "workers_as_python": self.pool.as_python(),
            "worker_restarts": self.pool.restarts,
            "worker_deaths": self.pool.deaths,
            "admitted": self.pool.admitted,
            "capacity": self.pool.capacity,
            "busy": self.pool.busy,
            "maps": list(changes),
            "map_status": {name: change or "ok" for name, change in changes.items()},
            "sessions": self.sessions.count,
            "max_sessions": self.sessions.max_sessions,
        }
        return body, 503 if status == "failing" else 200

    async def localize(self, request) -> tuple[dict, int, dict]:
        """``(body, status, headers)`` of one ``POST /v1/localize`` (module docstring)."""
        s = self.settings
        try:
            req = await read_localize_form(
                request, s.maps, s.max_image_bytes, body_timeout_s=s.body_timeout_s, budget=self.budget
            )
        except RequestError as exc:
            return self._refused(exc)
        refusal = self.watch.refusal(req.map_name)
        if refusal is not None:
            self.metrics.rejected.labels("map_changed").inc()
            return {"error": refusal}, 503, {"Retry-After": "60"}
        try:
            self.pool.admit()
        except Overloaded as exc:
            self.metrics.rejected.labels("overloaded").inc()
            return (
                {"error": f"server busy ({self.pool.admitted} requests admitted); retry later"},
                503,
                {"Retry-After": str(exc.retry_after_s)},
            )
        try:
            record = await self._run(req)
            refusal = self.watch.refusal(req.map_name)  # changed while the worker ran: not this answer
            if refusal is not None:
                self.metrics.rejected.labels("map_changed").inc()
                return {"error": refusal}, 503, {"Retry-After": "60"}
            self.metrics.outcomes.labels(str(record.get("status", "unknown"))).inc()
            return record, 200, {}
        except RequestError as exc:
            return self._refused(exc)
        except (QueueTimeout, WorkerDied) as exc:
            self.metrics.rejected.labels("timeout" if isinstance(exc, QueueTimeout) else "worker_died").inc()
            return {"error": str(exc)}, 503, {"Retry-After": "1"}
        except ServerFault as exc:
            self.metrics.rejected.labels("server_fault").inc()
            logger.error("localize %s on map %s failed: %s", req.name, req.map_name, exc.detail or exc.public)
            return {"error": self.scrub(exc.public)}, 500, {}
        except Exception:  # noqa: BLE001 - a bug: the traceback to the log, one line to the client
            self.metrics.rejected.labels("server_fault").inc()
            logger.exception("localize failed")
            return {"error": "internal error (logged on the server)"}, 500, {}
        finally:
            self.pool.release()

    async def _run(self, req) -> dict:
        if req.session is None:
            return await self.pool.run(worker.localize_request, req)
        entry = self.sessions.open(req, self.pool.alive())
        self.flush_drops()
        answered = False
        try:
            record = await self.pool.run(worker.session_frame, req, entry.generation, slot=entry.slot)
            answered = True
            return record
        except ServerFault:
            self.sessions.close_after_fault(entry)
            self.flush_drops()
            raise
        finally:
            self.sessions.done(entry, answered)

    def _refused(self, exc: RequestError) -> tuple[dict, int, dict]:
        reason = {408: "timeout", 413: "too_large", 503: "overloaded", 410: "session_gone"}.get(
            exc.status, "bad_request"
        )
        self.metrics.rejected.labels(reason).inc()
        headers = {"Connection": "close"} if exc.status in _CLOSE_AFTER else {}
        if exc.retry_after_s is not None:
            headers["Retry-After"] = str(exc.retry_after_s)
        return {"error": self.scrub(exc.message)}, exc.status, headers


def create_app(settings: ServeSettings):  # -> fastapi.FastAPI
    """The FastAPI app; its :class:`Service` is ``app.state.service`` (started by the app's
    lifespan unless started before, as ``planarloc serve`` does)."""
    fastapi = require("fastapi", "serve")
    responses = require("fastapi.responses", "serve")
    require("python_multipart", "serve")
    service = Service(settings)
    metrics = service.metrics

    def error(status: int, message: str, headers: dict | None = None):
        return responses.JSONResponse({"error": message}, status_code=status, headers=headers)

    @asynccontextmanager
    async def lifespan(_app):
        await service.start()
        try:
            yield
        finally:
            await service.close()

    app = fastapi.FastAPI(
        title="planarloc", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None
    )
    app.state.service = service
    app.state.pool = service.pool
    app.state.metrics = metrics

    @app.middleware("http")
    async def measure(request, call_next):
        t0 = time.perf_counter()
        path = request.url.path
        endpoint = path if path in ENDPOINTS else "other"
        guarded = settings.token and endpoint in ("/v1/localize", "/v1/maps", "/metrics")
        if guarded and not bearer_token_matches(request.headers.get("authorization", ""), settings.token):
            metrics.rejected.labels("unauthorized").inc()
            response = error(
                401,
                "missing or wrong bearer token (header 'Authorization: Bearer TOKEN')",
                {"WWW-Authenticate": "Bearer", "Connection": "close"},
            )
            metrics.observe(endpoint, 401, time.perf_counter() - t0)
            return response
        response = await call_next(request)
        metrics.observe(endpoint, response.status_code, time.perf_counter() - t0)
        return response

    @app.post("/v1/localize")
    # FastAPI reads the annotation at run time to pass the request; fastapi is the optional extra,
    # imported in this function, so mypy cannot name its type here.
    async def localize(request: fastapi.Request):  # type: ignore[name-defined]
        body, status, headers = await service.localize(request)
        if status == 200:
            return responses.Response(strict_json.dumps(body), media_type="application/json")
        return responses.JSONResponse(strict_json.to_jsonable(body), status_code=status, headers=headers)

    @app.get("/v1/maps")
    async def maps():
        return {"maps": [{**m, "status": service.watch.check(m["name"]) or "ok"} for m in service.summaries]}

    @app.get("/healthz")
    async def healthz():
        body, status = service.health()
        return responses.JSONResponse(strict_json.to_jsonable(body), status_code=status)

    @app.get("/metrics")
    async def prometheus():
        body, ctype = metrics.render()
        return responses.Response(body, media_type=ctype)

    @app.exception_handler(404)
    async def not_found(_request, _exc):
        return error(404, f"no such endpoint; endpoints: {', '.join(ENDPOINTS)}")

    @app.exception_handler(405)
    async def wrong_method(_request, _exc):
        return error(405, "method not allowed: POST /v1/localize, GET /v1/maps, /healthz, /metrics")

    return app


def header_timeout_protocol(timeout_s: float):  # -> a uvicorn HTTP protocol class
    """uvicorn's h11 protocol, closing connections whose request headers take longer than
    ``timeout_s`` to arrive (uvicorn bounds the idle time between requests, not the headers)."""
    h11 = require("h11", "serve")
    base = require("uvicorn.protocols.http.h11_impl", "serve").H11Protocol

    class HeaderTimeoutProtocol(base):  # type: ignore[misc, valid-type]
        _header_timer = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._arm()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state is h11.IDLE:  # a request's headers are still coming
                self._arm()
            else:
                self._disarm()

        def connection_lost(self, exc) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _arm(self) -> None:
            if self._header_timer is None:
                self._header_timer = self.loop.call_later(timeout_s, self._expire)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _expire(self) -> None:
            self._header_timer = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

    return HeaderTimeoutProtocol
