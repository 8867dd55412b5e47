"""A query from a place the map does not hold gets ``not_in_map`` with what was tried (issue 32),
and a query the map holds does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from record_schemas import check
from textured_images import textured_image

from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, localizer_config
from planarloc.localize.records import query_record
from planarloc.map.builder import build_map


@pytest.fixture(scope="module")
def office(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Localizer:
    path = build_map(read_dataset(tiny_world / "map", "tum"), tmp_path_factory.mktemp("map") / "office.db")
    return Localizer(path, localizer_config(structure="tracks"))


def test_another_place_is_not_in_map(office: Localizer, straight_corridor: Path) -> None:
    """Frames of another generated world (a corridor) and of random shapes, against the office."""
    camera = next(iter(office.map_cameras))
    corridor = read_dataset(straight_corridor / "query", "tum")
    frames = {q.name: q.path for q in corridor[:3]}
    rng = np.random.default_rng(0)
    frames.update({f"shapes-{k}": textured_image(rng, camera.height, camera.width) for k in range(2)})
    for name, frame in frames.items():
        est = office.localize(frame, camera)
        assert not est.success and est.status == "not_in_map", (name, est.status, est.message)
        assert est.pose is None and "no map image sees the query: tried" in est.message
        assert "the estimator said" in est.message  # its own reason is kept
        record = check("record", query_record(name, est))
        assert record["status"] == "not_in_map" and record["quat_wxyz"] is None


def test_a_place_the_map_holds_is_not_called_unseen(office: Localizer, tiny_world: Path) -> None:
    queries = read_dataset(tiny_world / "query", "tum")
    statuses = [office.localize(q.path, q.camera).status for q in queries]
    assert "not_in_map" not in statuses and statuses.count("success") >= len(queries) - 1, statuses
