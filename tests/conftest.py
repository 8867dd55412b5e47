"""Shared fixtures and helpers: a tiny rendered world (generated, never read from disk), and the
helper modules of ``tests/support`` (posed image folders, textured images) on the import path."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent / "support"))

# `planarloc localize` on a cold kernel cache compiles first here, as before the background compile
# (`--compile`'s default, auto, would start a detached compile that outlives the tests and competes with
# their workers); tests/cli/test_first_use.py runs the background path on purpose.
os.environ.setdefault("PLANARLOC_COMPILE", "wait")

from planarloc.synthetic.world.export import generate  # noqa: E402
from planarloc.synthetic.world.presets import get_preset, shrunk  # noqa: E402


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """office preset at 320x240 with 12 map and 6 query frames (TUM layout: map/, query/)."""
    config = shrunk(get_preset("office"), scale=0.5, n_map=12, n_query=6)
    return generate(config, tmp_path_factory.mktemp("world") / "office", seed=0)


@pytest.fixture(scope="session")
def straight_corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """corridor preset at 320x240, 10 map and 6 query frames, the query on the map's line (no
    lateral offset): collinear with the map images, the 2D-2D-only mode cannot fix its position."""
    import dataclasses

    config = shrunk(get_preset("corridor"), scale=0.5, n_map=10, n_query=6)
    config = dataclasses.replace(
        config, trajectory=dataclasses.replace(config.trajectory, lateral_offset=0.0)
    )
    return generate(config, tmp_path_factory.mktemp("world") / "corridor", seed=0)
