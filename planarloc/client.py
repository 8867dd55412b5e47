"""Client of the localization service (``planarloc serve``), over httpx (extra ``planarloc[serve]``).

Example:
    >>> from planarloc.client import Client                                   # doctest: +SKIP
    >>> with Client("http://127.0.0.1:8080", token="s3cret") as c:              # doctest: +SKIP
    ...     rec = c.localize("q.png", "PINHOLE 640 480 525 525 320 240", map="office")
    ...     rec["quat_wxyz"], rec["t"] if rec["success"] else rec["status"]
    ...     robot = c.session("robot-7", camera="PINHOLE 640 480 525 525 320 240", map="office")
    ...     for stamp, frame in stream:                                      # one stream per robot
    ...         rec = robot.localize(frame, stamp)   # status localized / predicted / lost, covariance

The bearer token can come from a file or the environment instead of the command line, where it
would show in the process list (:func:`resolve_token`).
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import TypedDict, Unpack

from planarloc.extras import require
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io.text import T_XYZW, camera_text, pose_text

#: Environment variable read for the token when neither a token nor a token file is given.
TOKEN_ENV = "PLANARLOC_TOKEN"
_MAX_TOKEN = 4096


def resolve_token(
    token: str | None = None, token_file: str | os.PathLike | None = None, env: str = TOKEN_ENV
) -> str | None:
    """The bearer token: ``token``, else the first line of ``token_file``, else ``$PLANARLOC_TOKEN``,
    else None.

    Raises:
        ValueError: both ``token`` and ``token_file``; an unreadable or empty token file; a token
            that cannot be sent in an HTTP header (not printable ASCII, spaces, longer than 4096).
    """
    if token is not None and token_file is not None:
        raise ValueError(
            "--token, --token-file: give one of them (--token-file keeps the token out of the process list)"
        )
    source = "--token"
    if token_file is not None:
        source = f"--token-file {token_file}"
        try:
            with open(token_file, "rb") as f:
                raw = f.read(_MAX_TOKEN + 2)
        except OSError as exc:
            raise ValueError(f"{source}: cannot read it ({exc.strerror or exc})") from None
        lines = raw.decode("utf-8", "replace").splitlines()
        token = lines[0].strip() if lines else ""
        if not token:
            raise ValueError(f"{source}: the file is empty; write the token on its first line")
    elif token is None and os.environ.get(env):
        source, token = f"${env}", os.environ[env].strip()
    if token is None:
        return None
    if not token or len(token) > _MAX_TOKEN or not token.isascii() or not token.isprintable() or " " in token:
        raise ValueError(f"{source}: a token is 1-{_MAX_TOKEN} printable ASCII characters without spaces")
    return token


class ServiceError(RuntimeError):
    """The service refused a request: ``status`` (HTTP code) and the server's one-line ``reason``."""

    def __init__(self, status: int, reason: str, retry_after_s: float | None = None) -> None:
        super().__init__(f"HTTP {status}: {reason}" if status else reason)
        self.status, self.reason, self.retry_after_s = status, reason, retry_after_s


class SessionRestarted(ServiceError):
    """The server no longer holds the session's stream (HTTP 410: evicted after being idle or
    because too many sessions were open, or its worker died). The frame was not localized;
    sending it again starts a new stream (:attr:`Session.restarts` counts them)."""


class QueryOptions(TypedDict, total=False):
    """Optional fields of a query, sent as given (None or left out: the server's default; ``planarloc
    serve --help``): keyword arguments of :meth:`Client.localize`, :meth:`Client.session` and
    :class:`Session`."""

    #: the map's name (needed when the server serves several)
    map: str | None
    #: hypothesis families, e.g. ``"auto"``, ``"2p1p"``
    method: str | None
    #: ``"none"`` or ``"tracks"``
    structure: str | None
    #: RANSAC seed
    seed: int | None


def _check_options(options: Mapping[str, object], where: str) -> None:
    """A keyword that is not a :class:`QueryOptions` field is a TypeError, as for any signature."""
    unknown = sorted(set(options) - set(QueryOptions.__annotations__))
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s): {', '.join(unknown)}")


class Client:
    """Talks to one server.

    Args:
        base_url: e.g. ``http://127.0.0.1:8080``.
        token: bearer token if the server was started with one (:func:`resolve_token`).
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
        return self._check(self._request(method, path, **kwargs))

    def _request(self, method: str, path: str, **kwargs: object):
        try:
            return self._http.request(method, path, **kwargs)
        except self._transport_error as exc:
            raise ServiceError(
                0, f"cannot reach {self._http.base_url}: {type(exc).__name__}: {exc}"
            ) from None

    def _check(self, response) -> dict:
        if response.status_code == 200:
            return response.json()
        try:
            reason = response.json().get("error", response.text)
        except ValueError:
            reason = response.text[:200]
        retry = response.headers.get("retry-after")
        kind = SessionRestarted if response.status_code == 410 else ServiceError
        raise kind(response.status_code, str(reason), float(retry) if retry and retry.isdigit() else None)

    def health(self) -> dict:
        """``GET /healthz`` (also when it answers 503: the body says what is failing)."""
        response = self._request("GET", "/healthz")
        if response.status_code == 503:
            return response.json()
        return self._check(response)

    def maps(self) -> list[dict]:
        """``GET /v1/maps``: name, images, cameras and completeness of each served map."""
        return self._send("GET", "/v1/maps")["maps"]

    def _post(self, fields: dict, fname: str, data: bytes) -> dict:
        fields = {k: v for k, v in fields.items() if v is not None}
        for attempt in range(self.retries + 1):
            try:
                return self._send("POST", "/v1/localize", data=fields, files={"image": (fname, data)})
            except ServiceError as exc:
                if exc.status != 503 or attempt == self.retries:
                    raise
                time.sleep(min(exc.retry_after_s or 1.0, 10.0))
        raise AssertionError("unreachable")

    def localize(
        self,
        image: str | Path | bytes,
        camera: Camera | str | None = None,
        *,
        name: str | None = None,
        gravity: tuple[float, float, float] | None = None,
        session: str | None = None,
        stamp: float | None = None,
        odometry: Pose | None = None,
        **options: Unpack[QueryOptions],
    ) -> dict:
        """``POST /v1/localize``; returns the per-query record (as ``planarloc localize`` writes it),
        or with ``session`` the per-frame record (as ``planarloc localize --sequence``; see :meth:`session`).

        Args:
            image: a JPEG/PNG file path or its bytes.
            camera: the query intrinsics (a :class:`Camera` or ``"MODEL W H PARAMS..."``); None: the
                served map's camera (when it has exactly one).
            name: the record's ``name`` (default: the file name, or ``"query.png"`` for bytes).
            gravity: an optional field, as ``options`` (see ``planarloc serve --help``).
            session, stamp, odometry: a frame of a robot's stream: its session id, its time (s)
                and its ``cam_from_odom`` wheel-odometry pose (sent as the camera's pose in the
                odometry frame, ``tx ty tz qx qy qz qw``).
            **options: :class:`QueryOptions`: ``map`` (needed when the server serves several),
                ``method``, ``structure``, ``seed``.

        Raises:
            ServiceError: 4xx (bad input, with the server's reason) or 5xx after ``retries``;
                :class:`SessionRestarted` for a session the server no longer holds.
        """
        _check_options(options, "Client.localize")
        seed = options.get("seed")
        if isinstance(image, bytes):
            data, fname = image, name or "query.png"
        else:
            data, fname = Path(image).read_bytes(), name or Path(image).name
        fields = {
            "camera": camera if camera is None or isinstance(camera, str) else camera_text(camera),
            "map": options.get("map"),
            "session": session,
            "stamp": None if stamp is None else repr(float(stamp)),
            "odometry": None if odometry is None else pose_text(odometry.inverse(), T_XYZW),
            "method": options.get("method"),
            "structure": options.get("structure"),
            "seed": None if seed is None else str(int(seed)),
            "gravity": None if gravity is None else " ".join(repr(float(g)) for g in gravity),
        }
        return self._post(fields, fname, data)

    def session(
        self,
        session_id: str | None = None,
        *,
        camera: Camera | str | None = None,
        **options: Unpack[QueryOptions],
    ) -> Session:
        """A robot's stream on the server (:class:`Session`: ``camera`` and ``options`` are sent with
        each frame); ``session_id`` default: a new UUID."""
        return Session(self, session_id or uuid.uuid4().hex, camera=camera, **options)


class Session:
    """One robot's stream on the server: frames localized in order by one ``SequenceLocalizer``
    kept by the server between requests (``planarloc serve``, field ``session``).

    Every frame's answer is the record ``planarloc localize --sequence`` writes per frame (``status``
    ``localized`` / ``predicted`` / ``lost``, ``quat_wxyz`` and ``t`` of ``cam_from_world``, the
    (6, 6) ``covariance_xyz_rotvec`` in ROS order (docs/conventions.md), ...) with ``session``
    ``{"id", "frame"}``. The server answers each frame with its own fix (``fixes="wait"``).

    Frames must come in time order (a stamp not after the last is refused with HTTP 409). When
    the server no longer holds the stream (evicted, or its worker died), :meth:`localize` raises
    :class:`SessionRestarted`; the next frame starts a new stream. A frame answered by a stream
    that restarted without a 410 (its frame number is not the next one, e.g. a restarted Ray
    replica) gets ``session.restarted = True`` in its record. :attr:`restarts` counts both.
    """

    def __init__(
        self,
        client: Client,
        session_id: str,
        *,
        camera: Camera | str | None = None,
        **options: Unpack[QueryOptions],
    ) -> None:
        _check_options(options, "Session")
        self.client, self.id, self.camera = client, str(session_id), camera
        self.map, self.method = options.get("map"), options.get("method")
        self.structure, self.seed = options.get("structure"), options.get("seed")
        self.frames = 0
        self.restarts = 0

    def localize(
        self,
        image: str | Path | bytes,
        stamp: float,
        odometry: Pose | None = None,
        *,
        name: str | None = None,
        gravity: tuple[float, float, float] | None = None,
    ) -> dict:
        """Localize the next frame (``stamp`` in seconds; ``odometry``: its ``cam_from_odom``)."""
        try:
            record = self.client.localize(
                image,
                self.camera,
                map=self.map,
                name=name,
                gravity=gravity,
                session=self.id,
                stamp=stamp,
                odometry=odometry,
                method=self.method,
                structure=self.structure,
                seed=self.seed,
            )
        except SessionRestarted:
            self.frames = 0
            self.restarts += 1
            raise
        info = record.get("session") or {}
        frame = int(info.get("frame", 0))
        if frame != self.frames + 1:  # the server restarted the stream without saying so (e.g. a Ray replica)
            self.restarts += 1
            record = {**record, "session": {**info, "restarted": True}}
        self.frames = frame
        return record
