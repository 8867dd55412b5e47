"""A running `planarloc serve` as the service tests see it (one module, not the serve conftest:
several test folders have a ``conftest`` and ``from conftest import`` depends on their order)."""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from planarloc.serve.launcher import start_server, stop_server

#: (world folder, map file, query camera) of the serve tests' world (the ``served_world`` fixture).
ServedWorld = tuple[Path, Path, str]


@dataclass(frozen=True)
class Served:
    url: str
    process: subprocess.Popen
    world: Path
    map_path: Path
    camera: str
    token: str


@contextlib.contextmanager
def serving(
    served_world: ServedWorld, options: list[str], token: str = "", env: dict | None = None
) -> Iterator[Served]:
    """`planarloc serve` of the served world's map as ``office`` with further ``options``, stopped on exit;
    ``token``: the one the server expects (``options`` or ``env`` give it to the server)."""
    world, map_path, camera = served_world
    url, proc = start_server(["--map", f"office={map_path}", *options], env=env)
    try:
        yield Served(url, proc, world, map_path, camera, token)
    finally:
        stop_server(proc)
