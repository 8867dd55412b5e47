"""The settings of ``planarloc serve``, with the defaults the command line shows."""

from __future__ import annotations

from dataclasses import dataclass

from planarloc.serve.requests import DEFAULT_MAX_IMAGE_BYTES, MapSet

DEFAULT_WORKERS = 2
DEFAULT_QUEUE = 8

__all__ = ["DEFAULT_MAX_IMAGE_BYTES", "DEFAULT_QUEUE", "DEFAULT_WORKERS", "ServeSettings"]


@dataclass(frozen=True)
class ServeSettings:
    """Settings of ``planarloc serve``: the maps, ``workers`` processes, at most ``queue_size``
    requests waiting beyond the running ones, the bearer ``token`` and the upload limit."""

    maps: MapSet
    workers: int = DEFAULT_WORKERS
    queue_size: int = DEFAULT_QUEUE
    token: str | None = None
    max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES
