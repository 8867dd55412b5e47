"""The localizer as a Ray Serve deployment, for a fleet (optional extra ``planarloc[ray]``).

One Ray Serve application per map, made of three deployments:

- ``localizer-<map>``: ``replicas`` replicas, each opens **its one map** once, read-only, and
  keeps it; they answer single queries. Ray Serve routes the requests over them; each takes
  ``max_ongoing_requests`` at a time, at most ``max_queued_requests`` more wait, beyond that Ray
  Serve answers 503.
- ``sessions-<map>-<k>`` for ``k < session_shards``: **one replica each**, holding the robot
  sessions (:mod:`planarloc.serve.sessions`) whose id hashes to ``k`` (SHA-1 of the id, so the
  same in every process). Ray Serve's own routing picks any replica of a deployment, so a
  session's state could otherwise be split; a one-replica shard per hash bucket keeps every
  frame of a session in one process. If a shard's replica dies, Ray Serve restarts it and its
  sessions start over (their next answer's ``session.frame`` restarts at 1; the client's
  :class:`~planarloc.client.Session` marks it ``restarted``). Scale sessions with more shards.
- ``ingress-<map>``: reads and checks the form (:mod:`planarloc.serve.form`, the limits of
  ``planarloc serve``) and sends the request to the pool or to its session's shard.

A replica speaks the API of ``planarloc serve``:

    POST /v1/maps/<name>/localize   multipart form: image, camera, gravity, session, stamp,
                                     odometry, method, structure, seed  ->  the record
                                     ``planarloc localize`` (or ``--sequence``) writes

and Python callers can use the ingress handle: ``handle.answer.remote(request)`` with a
:class:`planarloc.serve.requests.LocalizeRequest` returns ``(body, status, headers)``.

Deploy (the map files must be readable on every node, planarloc installed on every node)::

    import ray
    from planarloc.serve.ray_serve import deploy_fleet
    ray.init(address="auto")                       # or ray.init() for a local instance
    handles = deploy_fleet({"office": "office.db", "lab": "lab.db"}, replicas=4, session_shards=2,
                           host="127.0.0.1", port=8000)
    # curl -F image=@q.png -F 'camera=PINHOLE 640 480 525 525 320 240' \\
    #      http://127.0.0.1:8000/v1/maps/office/localize

Scale a map's replicas by deploying it again with another ``replicas``; ``serve.delete(
"planarloc-office")`` removes it.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping
from pathlib import Path

from planarloc.extras import require
from planarloc.io import strict_json
from planarloc.serve.form import FORM_OVERHEAD_BYTES, UploadBudget, read_localize_form
from planarloc.serve.map_watch import MapWatch
from planarloc.serve.requests import (
    DEFAULT_MAX_IMAGE_BYTES,
    LocalizeRequest,
    MapSet,
    RequestError,
    ServerFault,
)
from planarloc.serve.sessions import SessionStates, SessionTable
from planarloc.serve.settings import DEFAULT_MAX_SESSIONS, DEFAULT_SESSION_IDLE_S
from planarloc.serve.worker import compiled_now, localize_with, session_frame_with, start_kernels

logger = logging.getLogger(__name__)
Answer = tuple[dict, int, dict]


def session_shard(session: str, shards: int) -> int:
    """The shard of a session id: SHA-1 of the id modulo ``shards`` (the same in every process)."""
    return int.from_bytes(hashlib.sha1(session.encode()).digest()[:8], "big") % int(shards)


class LocalizerReplica:
    """One replica: a Localizer on one map; with ``sessions`` also the sessions of one shard.

    :meth:`answer` never raises for a request: it returns ``(body, status, headers)`` as
    ``planarloc serve`` would answer it.
    """

    def __init__(
        self,
        map_name: str,
        map_path: str,
        max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES,
        sessions: bool = False,
        max_sessions: int = DEFAULT_MAX_SESSIONS,
        session_idle_s: float = DEFAULT_SESSION_IDLE_S,
    ) -> None:
        from concurrent.futures import ThreadPoolExecutor

        from planarloc.localize.localizer import Localizer

        self.map_name = map_name
        self.maps = MapSet({map_name: Path(map_path)})
        self.max_image_bytes = int(max_image_bytes)
        self.watch = MapWatch(self.maps.paths)
        self.sessions = SessionTable(1, max_sessions, session_idle_s) if sessions else None
        self._states = SessionStates()
        self.budget = UploadBudget(4 * (self.max_image_bytes + FORM_OVERHEAD_BYTES))
        # The map (SQLite) is opened and used in one thread, which also keeps the CPU work off
        # the replica's event loop; the replica computes one request at a time, in arrival order.
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="planarloc-localizer")
        self.localizer = self._thread.submit(Localizer, Path(map_path)).result()
        # On an empty kernel cache the replicas share one compile, as Python meanwhile (in the
        # thread that computes: the kernels switch back between two requests).
        self._first_use = self._thread.submit(start_kernels, [self.localizer]).result()

    def _compute(self, req: LocalizeRequest, generation: int | None) -> dict:
        compiled_now(self._first_use)
        if generation is None:
            return localize_with(self.localizer, req)
        return session_frame_with(self.localizer, self._states, req, generation)

    async def answer(self, req: LocalizeRequest) -> Answer:
        """``(body, status, headers)`` of one validated request."""
        import asyncio

        refusal = self.watch.refusal(req.map_name)
        if refusal is not None:
            return {"error": refusal}, 503, {"Retry-After": "60"}
        entry = None
        try:
            if req.session is not None:
                if self.sessions is None:
                    raise RequestError(
                        400,
                        "session: this deployment has no session shards (deploy_fleet(session_shards=...))",
                    )
                entry = self.sessions.open(req, [True])
                self._states.drop([e.id for e in self.sessions.take_drops()])
            record = await asyncio.wrap_future(
                self._thread.submit(self._compute, req, None if entry is None else entry.generation)
            )
            if entry is not None:
                self.sessions.done(entry, True)  # type: ignore[union-attr]
                entry = None
            return record, 200, {}
        except RequestError as exc:
            headers = {} if exc.retry_after_s is None else {"Retry-After": str(exc.retry_after_s)}
            return {"error": exc.message}, exc.status, headers
        except ServerFault as exc:
            logger.error("localize %s failed: %s", req.name, exc.detail or exc.public)
            if entry is not None:
                self.sessions.close_after_fault(entry)  # type: ignore[union-attr]
            return {"error": exc.public}, 500, {}
        except Exception:  # noqa: BLE001 - a bug: the traceback to the replica log, one line to the client
            logger.exception("localize failed")
            return {"error": "internal error (logged on the server)"}, 500, {}
        finally:
            if entry is not None:
                self.sessions.done(entry, False)  # type: ignore[union-attr]

    async def __call__(self, request):  # starlette.requests.Request -> starlette Response
        return await respond(request, self.maps, self.max_image_bytes, self.budget, self.answer)


async def respond(request, maps: MapSet, max_image_bytes: int, budget: UploadBudget, answer):
    """Read the form of an HTTP request and answer it with ``await answer(req)`` (a Starlette response)."""
    from starlette.responses import JSONResponse, Response

    if request.method != "POST":
        return JSONResponse({"error": "POST a multipart form to .../localize"}, status_code=405)
    try:
        req = await read_localize_form(request, maps, max_image_bytes, budget=budget)
    except RequestError as exc:
        headers = {"Connection": "close"} if exc.status in (400, 408, 413, 415) else {}
        return JSONResponse({"error": exc.message}, status_code=exc.status, headers=headers)
    body, status, headers = await answer(req)
    if status == 200:
        return Response(strict_json.dumps(body), media_type="application/json")
    return JSONResponse(strict_json.to_jsonable(body), status_code=status, headers=headers)


class LocalizerIngress:
    """The HTTP entry of one map: reads the form, sends the request to the pool or its session's shard."""

    def __init__(self, map_name: str, map_path: str, max_image_bytes: int, pool, *shards) -> None:
        self.maps = MapSet({map_name: Path(map_path)})
        self.max_image_bytes = int(max_image_bytes)
        self.budget = UploadBudget(8 * (self.max_image_bytes + FORM_OVERHEAD_BYTES))
        self.pool, self.shards = pool, list(shards)

    async def answer(self, req: LocalizeRequest) -> Answer:
        if req.session is not None and self.shards:
            handle = self.shards[session_shard(req.session, len(self.shards))]
        else:
            handle = self.pool
        return await handle.answer.remote(req)

    async def __call__(self, request):
        return await respond(request, self.maps, self.max_image_bytes, self.budget, self.answer)


def localizer_app(
    map_name: str,
    map_path: str | Path,
    replicas: int = 1,
    max_ongoing_requests: int = 2,
    max_queued_requests: int = 16,
    session_shards: int = 1,
    max_sessions_per_shard: int = DEFAULT_MAX_SESSIONS,
    session_idle_s: float = DEFAULT_SESSION_IDLE_S,
    max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES,
):
    """The bound Ray Serve application of one map (module docstring): ``replicas`` pool replicas and
    ``session_shards`` one-replica session shards (1 CPU each), behind one ingress."""
    serve = require("ray.serve", "ray")
    if replicas < 1:
        raise ValueError(f"replicas: need at least 1, got {replicas}")
    if session_shards < 0:
        raise ValueError(f"session_shards: must be >= 0, got {session_shards}")
    path = str(Path(map_path).resolve())
    limits = {
        "max_ongoing_requests": int(max_ongoing_requests),
        "max_queued_requests": int(max_queued_requests),
    }
    pool = serve.deployment(
        LocalizerReplica,
        name=f"localizer-{map_name}",
        num_replicas=int(replicas),
        ray_actor_options={"num_cpus": 1},
        **limits,
    ).bind(map_name, path, max_image_bytes)
    shards = [
        serve.deployment(
            LocalizerReplica,
            name=f"sessions-{map_name}-{k}",
            num_replicas=1,
            ray_actor_options={"num_cpus": 1},
            **limits,
        ).bind(map_name, path, max_image_bytes, True, max_sessions_per_shard, session_idle_s)
        for k in range(int(session_shards))
    ]
    ingress = serve.deployment(
        LocalizerIngress,
        name=f"ingress-{map_name}",
        num_replicas=1,
        ray_actor_options={"num_cpus": 0},
        max_ongoing_requests=4 * (int(replicas) + len(shards)) * int(max_ongoing_requests),
    )
    return ingress.bind(map_name, path, max_image_bytes, pool, *shards)


def deploy_fleet(
    maps: Mapping[str, str | Path],
    replicas: int = 1,
    host: str = "127.0.0.1",
    port: int = 8000,
    max_ongoing_requests: int = 2,
    max_queued_requests: int = 16,
    session_shards: int = 1,
) -> dict:
    """Deploy one application per map on the connected Ray cluster; returns ``{name: ingress handle}``.

    Routes: ``POST /v1/maps/<name>/localize`` on ``host:port`` (Ray Serve's HTTP proxy).
    """
    serve = require("ray.serve", "ray")
    checked = MapSet.from_specs([f"{name}={path}" for name, path in maps.items()])
    serve.start(http_options={"host": host, "port": int(port)})
    handles = {}
    for name, path in checked.paths.items():
        app = localizer_app(name, path, replicas, max_ongoing_requests, max_queued_requests, session_shards)
        handles[name] = serve.run(app, name=f"planarloc-{name}", route_prefix=f"/v1/maps/{name}/localize")
    return handles
