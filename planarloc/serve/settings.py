"""The settings of ``planarloc serve``, with the defaults the command line shows."""

from __future__ import annotations

from dataclasses import dataclass

from planarloc.serve.requests import DEFAULT_MAX_IMAGE_BYTES, MapSet

DEFAULT_WORKERS = 2
DEFAULT_QUEUE = 8
#: Time for a whole request body to arrive (seconds).
DEFAULT_BODY_TIMEOUT_S = 30.0
#: Longest wait of an admitted request for a worker, and longest localization (seconds).
DEFAULT_QUEUE_TIMEOUT_S = 30.0
DEFAULT_JOB_TIMEOUT_S = 120.0
#: Sessions kept at once, and their longest time without a frame (seconds).
DEFAULT_MAX_SESSIONS = 64
DEFAULT_SESSION_IDLE_S = 300.0
#: Time for a request's headers to arrive once a connection is open (seconds).
DEFAULT_HEADER_TIMEOUT_S = 10.0
#: Environment variable holding the bearer token (instead of ``--token``).
TOKEN_ENV = "PLANARLOC_TOKEN"

__all__ = [
    "DEFAULT_BODY_TIMEOUT_S",
    "DEFAULT_HEADER_TIMEOUT_S",
    "DEFAULT_JOB_TIMEOUT_S",
    "DEFAULT_MAX_IMAGE_BYTES",
    "DEFAULT_MAX_SESSIONS",
    "DEFAULT_QUEUE",
    "DEFAULT_QUEUE_TIMEOUT_S",
    "DEFAULT_SESSION_IDLE_S",
    "DEFAULT_WORKERS",
    "TOKEN_ENV",
    "ServeSettings",
]


@dataclass(frozen=True)
class ServeSettings:
    """Settings of ``planarloc serve``.

    Attributes:
        maps: the served maps.
        workers: localization processes.
        queue_size: admitted requests waiting beyond the running ones.
        token: bearer token for ``/v1/*`` and ``/metrics`` (None: open).
        max_image_bytes: upload limit of the image.
        header_timeout_s, body_timeout_s: time for a request's headers, then for its body.
        queue_timeout_s: longest wait of an admitted request for a worker (then 503).
        job_timeout_s: longest localization; beyond it the worker is replaced (503).
        max_sessions, session_idle_s: sessions kept at once, and their longest idle time.
    """

    maps: MapSet
    workers: int = DEFAULT_WORKERS
    queue_size: int = DEFAULT_QUEUE
    token: str | None = None
    max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES
    header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S
    body_timeout_s: float = DEFAULT_BODY_TIMEOUT_S
    queue_timeout_s: float = DEFAULT_QUEUE_TIMEOUT_S
    job_timeout_s: float = DEFAULT_JOB_TIMEOUT_S
    max_sessions: int = DEFAULT_MAX_SESSIONS
    session_idle_s: float = DEFAULT_SESSION_IDLE_S
