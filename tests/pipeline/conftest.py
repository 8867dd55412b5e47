"""A tiny rendered world shared by the end-to-end tests (generated, never read from disk)."""

from __future__ import annotations

from pathlib import Path

import pytest

from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """office preset at 320x240 with 12 map and 6 query frames (TUM layout: map/, query/)."""
    config = shrunk(get_preset("office"), scale=0.5, n_map=12, n_query=6)
    return generate(config, tmp_path_factory.mktemp("world") / "office", seed=0)
