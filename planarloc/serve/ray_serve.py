"""The localizer as a Ray Serve deployment, for a fleet (optional extra ``planarloc[ray]``).

One Ray Serve application per map; each application is a deployment of ``replicas`` replicas,
and every replica opens **its one map** once, read-only, and keeps it. Ray Serve routes the
requests over the replicas; each replica takes ``max_ongoing_requests`` at a time, at most
``max_queued_requests`` more wait, beyond that Ray Serve answers 503. A replica speaks the same
API as ``planarloc serve``:

    POST /v1/maps/<name>/localize   multipart form: image, camera, gravity, session, method,
                                     structure, seed  ->  the record ``planarloc localize`` writes

and Python callers can use the deployment handle: ``handle.localize.remote(request)`` with a
:class:`planarloc.serve.requests.LocalizeRequest`.

Deploy (the map files must be readable on every node, planarloc installed on every node)::

    import ray
    from planarloc.serve.ray_serve import deploy_fleet
    ray.init(address="auto")                       # or ray.init() for a local instance
    handles = deploy_fleet({"office": "office.db", "lab": "lab.db"}, replicas=4,
                           host="127.0.0.1", port=8000)
    # curl -F image=@q.png -F 'camera=PINHOLE 640 480 525 525 320 240' \\
    #      http://127.0.0.1:8000/v1/maps/office/localize

Scale a map's replicas by deploying it again with another ``replicas``; ``serve.delete(
"planarloc-office")`` removes it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path

from planarloc.extras import require
from planarloc.serve.requests import DEFAULT_MAX_IMAGE_BYTES, LocalizeRequest, MapSet, RequestError


class LocalizerReplica:
    """One replica: a Localizer on one map (the body of the Ray Serve deployment)."""

    def __init__(self, map_name: str, map_path: str, max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES) -> None:
        from concurrent.futures import ThreadPoolExecutor

        from planarloc.localize.localizer import Localizer

        self.maps = MapSet({map_name: Path(map_path)})
        self.max_image_bytes = int(max_image_bytes)
        # The map (SQLite) is opened and used in one thread, which also keeps the CPU work off
        # the replica's event loop; the replica computes one request at a time.
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="planarloc-localizer")
        self.localizer = self._thread.submit(Localizer, Path(map_path)).result()

    def _submit(self, req: LocalizeRequest):
        from planarloc.serve.worker import localize_with

        return self._thread.submit(localize_with, self.localizer, req)

    def localize(self, req: LocalizeRequest) -> dict:
        """The per-query record (same as ``planarloc localize`` and ``planarloc serve``)."""
        return self._submit(req).result()

    async def __call__(self, request):  # starlette.requests.Request -> starlette Response
        import asyncio

        from starlette.responses import JSONResponse, Response

        from planarloc.geometry.validation import InputError
        from planarloc.serve.form import read_localize_form

        if request.method != "POST":
            return JSONResponse({"error": "POST a multipart form to .../localize"}, status_code=405)
        try:
            req = await read_localize_form(request, self.maps, self.max_image_bytes)
            record = await asyncio.wrap_future(self._submit(req))
        except RequestError as exc:
            return JSONResponse({"error": exc.message}, status_code=exc.status)
        except InputError as exc:
            return JSONResponse({"error": " ".join(str(exc).split())}, status_code=400)
        except Exception as exc:  # noqa: BLE001 - a bug: one line to the client, traceback in the replica log
            logging.getLogger(__name__).exception("localize failed")
            return JSONResponse(
                {"error": f"internal error: {type(exc).__name__}: {exc}"[:300]}, status_code=500
            )
        return Response(json.dumps(record), media_type="application/json")


def localizer_app(
    map_name: str,
    map_path: str | Path,
    replicas: int = 1,
    max_ongoing_requests: int = 2,
    max_queued_requests: int = 16,
):
    """The bound Ray Serve application of one map (``replicas`` replicas, 1 CPU each).

    Each replica takes ``max_ongoing_requests`` at a time (one computes, the others wait in it);
    at most ``max_queued_requests`` more wait in the caller/proxy, beyond that Ray Serve answers 503.
    """
    serve = require("ray.serve", "ray")
    if replicas < 1:
        raise ValueError(f"replicas: need at least 1, got {replicas}")
    deployment = serve.deployment(
        LocalizerReplica,
        name=f"localizer-{map_name}",
        num_replicas=int(replicas),
        max_ongoing_requests=int(max_ongoing_requests),
        max_queued_requests=int(max_queued_requests),
        ray_actor_options={"num_cpus": 1},
    )
    return deployment.bind(map_name, str(Path(map_path).resolve()))


def deploy_fleet(
    maps: Mapping[str, str | Path],
    replicas: int = 1,
    host: str = "127.0.0.1",
    port: int = 8000,
    max_ongoing_requests: int = 2,
    max_queued_requests: int = 16,
) -> dict:
    """Deploy one application per map on the connected Ray cluster; returns ``{name: handle}``.

    Routes: ``POST /v1/maps/<name>/localize`` on ``host:port`` (Ray Serve's HTTP proxy).
    """
    serve = require("ray.serve", "ray")
    checked = MapSet.from_specs([f"{name}={path}" for name, path in maps.items()])
    serve.start(http_options={"host": host, "port": int(port)})
    handles = {}
    for name, path in checked.paths.items():
        app = localizer_app(name, path, replicas, max_ongoing_requests, max_queued_requests)
        handles[name] = serve.run(app, name=f"planarloc-{name}", route_prefix=f"/v1/maps/{name}/localize")
    return handles
