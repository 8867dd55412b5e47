"""A real `planarloc serve` on a free loopback port, serving a map of a tiny rendered world."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from served import Served, ServedWorld, serving

pytest.importorskip("fastapi", reason="the serve extra is not installed (pip install 'planarloc[serve]')")
pytest.importorskip("httpx", reason="the serve extra is not installed (pip install 'planarloc[serve]')")

from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.map.builder import build_map  # noqa: E402
from planarloc.synthetic.world.export import generate  # noqa: E402
from planarloc.synthetic.world.presets import get_preset, shrunk  # noqa: E402

TOKEN = "test-token"


@pytest.fixture(scope="session")
def served_world(tmp_path_factory: pytest.TempPathFactory) -> ServedWorld:
    """(world folder, map file, query camera) of the office preset at 320x240, 12 map / 6 query frames."""
    config = shrunk(get_preset("office"), scale=0.5, n_map=12, n_query=6)
    world = generate(config, tmp_path_factory.mktemp("world") / "office", seed=0)
    map_path = build_map(read_dataset(world / "map", "tum"), tmp_path_factory.mktemp("maps") / "office.db")
    camera = (world / "query" / "camera.txt").read_text().splitlines()[-1]
    return world, map_path, camera


@pytest.fixture(scope="module")
def server(served_world: ServedWorld) -> Iterator[Served]:
    _world, map_path, _camera = served_world
    options = ["--workers", "2", "--queue", "2", "--token", TOKEN, "--max-image-mb", "1"]
    with serving(served_world, ["--map", f"second={map_path}", *options], TOKEN) as served:
        yield served
