"""The localization service: a FastAPI app over a :class:`~planarloc.serve.worker_pool.WorkerPool`.

Endpoints:

- ``POST /v1/localize`` — multipart form: ``image`` (JPEG/PNG file), and optionally ``camera``
  (``MODEL W H PARAMS...``; default: the map's, when it has one), ``map``, ``gravity``
  (``gx gy gz``), ``session``, ``method``, ``structure``, ``seed``. Answers the JSON
  ``planarloc localize`` writes per query (:func:`planarloc.localize.records.query_record`). A failed localization is a 200 with
  ``success: false`` and its status; a bad request is a 4xx with ``{"error": "<one line>"}``;
  overload is a 503 with ``Retry-After``; a worker that died mid-request is a 503 too.
- ``GET /v1/maps`` — the served maps (name, images, cameras, complete).
- ``GET /healthz`` — liveness and pool state (no token needed).
- ``GET /metrics`` — Prometheus exposition (:class:`~planarloc.serve.metrics.ServiceMetrics`).

With a token, ``/v1/*`` and ``/metrics`` need ``Authorization: Bearer <token>``.
"""

# No `from __future__ import annotations`: FastAPI reads the handlers' annotations at definition time.
import hmac
import json
import logging
import time
from contextlib import asynccontextmanager

from planarloc.extras import require
from planarloc.geometry.validation import InputError
from planarloc.io.text import camera_text
from planarloc.map.store import MapDatabase
from planarloc.serve import worker
from planarloc.serve.form import read_localize_form
from planarloc.serve.metrics import ServiceMetrics
from planarloc.serve.requests import MapSet, RequestError
from planarloc.serve.settings import ServeSettings
from planarloc.serve.worker_pool import Overloaded, WorkerDied, WorkerPool

logger = logging.getLogger(__name__)

ENDPOINTS = ("/v1/localize", "/v1/maps", "/healthz", "/metrics")


def map_summaries(maps: MapSet) -> list[dict]:
    """Name, image count, cameras and completeness of each served map (never its path)."""
    out = []
    for name, path in maps.paths.items():
        with MapDatabase.open(path, mode="r") as db:
            cameras = sorted({camera_text(p.camera) for p in db.posed_images()})
            out.append({"name": name, "images": db.num_images(), "complete": bool(db.is_complete), "cameras": cameras})
    return out


def create_app(settings: ServeSettings):  # -> fastapi.FastAPI
    """The FastAPI app; the worker pool starts with the app's lifespan."""
    fastapi = require("fastapi", "serve")
    responses = require("fastapi.responses", "serve")
    require("multipart", "serve")  # python-multipart, for the form parser
    pool = WorkerPool(settings.maps.paths, settings.workers, settings.queue_size)
    metrics = ServiceMetrics(pool)
    summaries = map_summaries(settings.maps)

    def error(status: int, message: str, headers: dict | None = None):
        return responses.JSONResponse({"error": message}, status_code=status, headers=headers)

    @asynccontextmanager
    async def lifespan(_app):
        await pool.start()
        logger.info("serving %s with %d workers", ", ".join(settings.maps.paths), pool.workers)
        try:
            yield
        finally:
            await pool.close()

    app = fastapi.FastAPI(
        title="planarloc", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None
    )
    app.state.pool = pool
    app.state.metrics = metrics

    @app.middleware("http")
    async def measure(request, call_next):
        t0 = time.perf_counter()
        path = request.url.path
        endpoint = path if path in ENDPOINTS else "other"
        if settings.token and endpoint in ("/v1/localize", "/v1/maps", "/metrics"):
            auth = request.headers.get("authorization", "")
            if not hmac.compare_digest(auth.encode(), f"Bearer {settings.token}".encode()):
                metrics.rejected.labels("unauthorized").inc()
                response = error(
                    401,
                    "missing or wrong bearer token (header 'Authorization: Bearer TOKEN')",
                    {"WWW-Authenticate": "Bearer"},
                )
                metrics.observe(endpoint, 401, time.perf_counter() - t0)
                return response
        response = await call_next(request)
        metrics.observe(endpoint, response.status_code, time.perf_counter() - t0)
        return response

    @app.post("/v1/localize")
    async def localize(request: fastapi.Request):
        try:
            pool.admit()
        except Overloaded as exc:
            metrics.rejected.labels("overloaded").inc()
            return error(
                503,
                f"server busy ({pool.admitted} requests admitted); retry later",
                {"Retry-After": str(exc.retry_after_s)},
            )
        try:
            req = await read_localize_form(request, settings.maps, settings.max_image_bytes)
            try:
                record = await pool.run(worker.localize_request, req)
            except InputError as exc:  # bad options found by the localizer itself
                raise RequestError(400, str(exc)) from None
            metrics.outcomes.labels(record.get("status", "unknown")).inc()
            return responses.Response(json.dumps(record), media_type="application/json")
        except RequestError as exc:
            metrics.rejected.labels("bad_request").inc()
            return error(exc.status, exc.message)
        except WorkerDied as exc:
            metrics.rejected.labels("worker_died").inc()
            return error(503, str(exc), {"Retry-After": "1"})
        except Exception as exc:  # noqa: BLE001 - a bug: keep the traceback in the log, answer one line
            logger.exception("localize failed")
            return error(500, f"internal error: {type(exc).__name__}: {exc}"[:300])
        finally:
            pool.release()

    @app.get("/v1/maps")
    async def maps():
        return {"maps": summaries}

    @app.get("/healthz")
    async def healthz():
        alive = sum(p is not None for p in pool.pids)
        return responses.JSONResponse(
            {
                "status": "ok" if alive == pool.workers else "degraded",
                "workers": pool.workers,
                "workers_alive": alive,
                "worker_restarts": pool.restarts,
                "admitted": pool.admitted,
                "capacity": pool.capacity,
                "maps": list(settings.maps.paths),
            },
            status_code=200 if alive else 503,
        )

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
