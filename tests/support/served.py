"""A running `planarloc serve` as the service tests see it (one module, not the serve conftest:
several test folders have a ``conftest`` and ``from conftest import`` depends on their order)."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Served:
    url: str
    process: subprocess.Popen
    world: Path
    map_path: Path
    camera: str
    token: str
