"""Client of the localization service (``planarloc serve``), over httpx (extra ``planarloc[serve]``).

Example:
    >>> from planarloc.client import Client                                   # doctest: +SKIP
    >>> with Client("http://127.0.0.1:8080", token="s3cret") as c:              # doctest: +SKIP
    ...     rec = c.localize("q.png", "PINHOLE 640 480 525 525 320 240", map="office")
    ...     rec["quat_wxyz"], rec["t"] if rec["success"] else rec["status"]
"""

from __future__ import annotations

import time
from pathlib import Path

from planarloc.extras import require
from planarloc.geometry.camera import Camera
from planarloc.io.text import camera_text


class ServiceError(RuntimeError):
    """The service refused a request: ``status`` (HTTP code) and the server's one-line ``reason``."""

    def __init__(self, status: int, reason: str, retry_after_s: float | None = None) -> None:
        super().__init__(f"HTTP {status}: {reason}" if status else reason)
        self.status, self.reason, self.retry_after_s = status, reason, retry_after_s


class Client:
    """Talks to one server.

    Args:
        base_url: e.g. ``http://127.0.0.1:8080``.
        token: bearer token if the server was started with ``--token``.
        timeout: seconds per request.
        retries: how often a 503 (busy, worker died) is retried, waiting ``Retry-After`` (bounded).
    """

    def __init__(
        self, base_url: str, token: str | None = None, timeout: float = 120.0, retries: int = 3
    ) -> None:
        httpx = require("httpx", "serve")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout)
        self.retries = int(retries)
        self._transport_error = httpx.TransportError

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, method: str, path: str, **kwargs: object) -> dict:
        try:
            response = self._http.request(method, path, **kwargs)
        except self._transport_error as exc:
            raise ServiceError(
                0, f"cannot reach {self._http.base_url}: {type(exc).__name__}: {exc}"
            ) from None
        return self._check(response)

    def _check(self, response) -> dict:
        if response.status_code == 200:
            return response.json()
        try:
            reason = response.json().get("error", response.text)
        except ValueError:
            reason = response.text[:200]
        retry = response.headers.get("retry-after")
        raise ServiceError(
            response.status_code, str(reason), float(retry) if retry and retry.isdigit() else None
        )

    def health(self) -> dict:
        """``GET /healthz``."""
        return self._send("GET", "/healthz")

    def maps(self) -> list[dict]:
        """``GET /v1/maps``: name, images, cameras and completeness of each served map."""
        return self._send("GET", "/v1/maps")["maps"]

    def localize(
        self,
        image: str | Path | bytes,
        camera: Camera | str | None = None,
        *,
        map: str | None = None,
        name: str | None = None,
        gravity: tuple[float, float, float] | None = None,
        session: str | None = None,
        method: str | None = None,
        structure: str | None = None,
        seed: int | None = None,
    ) -> dict:
        """``POST /v1/localize``; returns the per-query record (as ``planarloc localize`` writes it).

        Args:
            image: a JPEG/PNG file path or its bytes.
            camera: the query intrinsics (a :class:`Camera` or ``"MODEL W H PARAMS..."``); None: the
                served map's camera (when it has exactly one).
            map: map name (needed when the server serves several).
            name: the record's ``name`` (default: the file name, or ``"query.png"`` for bytes).
            gravity, session, method, structure, seed: optional fields (see ``planarloc serve --help``).

        Raises:
            ServiceError: 4xx (bad input, with the server's reason) or 5xx after ``retries``.
        """
        if isinstance(image, bytes):
            data, fname = image, name or "query.png"
        else:
            data, fname = Path(image).read_bytes(), name or Path(image).name
        fields = {
            "camera": camera if camera is None or isinstance(camera, str) else camera_text(camera),
            "map": map,
            "session": session,
            "method": method,
            "structure": structure,
            "seed": None if seed is None else str(int(seed)),
            "gravity": None if gravity is None else " ".join(repr(float(g)) for g in gravity),
        }
        fields = {k: v for k, v in fields.items() if v is not None}
        for attempt in range(self.retries + 1):
            try:
                return self._send("POST", "/v1/localize", data=fields, files={"image": (fname, data)})
            except ServiceError as exc:
                if exc.status != 503 or attempt == self.retries:
                    raise
                time.sleep(min(exc.retry_after_s or 1.0, 10.0))
        raise AssertionError("unreachable")
