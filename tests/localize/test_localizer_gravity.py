"""Gravity through the pipeline: stored in the map, given to every reference and to the estimator."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from planarloc.evaluation.queries import gravity_from_truth
from planarloc.features.images import read_gray
from planarloc.geometry.validation import InputError
from planarloc.gravity.world import WorldDown
from planarloc.io.datasets import read_dataset
from planarloc.localize import localizer as localizer_module
from planarloc.localize.localizer import Localizer
from planarloc.map.builder import build_map
from planarloc.map.gravity import map_gravity, store_map_gravity
from planarloc.map.schema import GRAVITY_META
from planarloc.map.store import MapDatabase
from planarloc.robust.result import PoseEstimate


@pytest.fixture(scope="module")
def small_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list, list]:
    map_images = read_dataset(tiny_world / "map", "tum")[:8]
    queries = read_dataset(tiny_world / "query", "tum")
    path = tmp_path_factory.mktemp("gmap") / "map.db"
    build_map(map_images, path)
    return path, map_images, queries


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> list[dict]:
    """Replaces the estimator in the localizer by a recorder of its arguments."""
    calls: list[dict] = []

    def fake(camera, pairs, method, options, query_gravity=None):
        calls.append({"pairs": pairs, "query_gravity": query_gravity})
        return PoseEstimate(None, False, "recorded", "", [np.zeros(len(p), bool) for p in pairs])

    monkeypatch.setattr(localizer_module, "estimate_absolute_pose", fake)
    return calls


def test_generated_world_map_stores_declared_gravity(small_map: tuple) -> None:
    path, _, _ = small_map
    with MapDatabase.open(path, mode="r") as db:
        rep = map_gravity(db)
        assert json.loads(db.get_meta(GRAVITY_META))["source"] == "declared"
    assert rep.source == "declared" and rep.g_world == (0.0, 1.0, 0.0)
    assert abs(rep.pitch_deg) < 5 and abs(rep.roll_deg) < 5  # the office robot's camera is nearly level


def test_references_get_their_gravity_and_the_query_its_own(small_map: tuple, captured: list[dict]) -> None:
    path, map_images, queries = small_map
    loc = Localizer(path)
    poses = {m.name: m.cam_from_world for m in map_images}
    image = read_gray(queries[0].path)
    loc.localize(image, queries[0].camera, references=list(poses)[:4], gravity=[0.0, 2.0, 0.2])
    loc.localize(image, queries[0].camera, references=list(poses)[:4])
    (first, second) = captured
    assert len(first["pairs"]) >= 2
    for pair in first["pairs"]:
        name = next(n for n, p in poses.items() if p is pair.ref_pose or np.allclose(p.R, pair.ref_pose.R))
        np.testing.assert_allclose(pair.ref_gravity, poses[name].R @ [0.0, 1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(first["query_gravity"], np.array([0.0, 2.0, 0.2]) / np.hypot(2.0, 0.2))
    assert second["query_gravity"] is None


def test_bad_query_gravity_fails_before_any_work(small_map: tuple, captured: list[dict]) -> None:
    path, _, queries = small_map
    loc = Localizer(path)
    for bad in ([0, 0, 0], [0, 1], [np.nan, 1, 0]):
        with pytest.raises(InputError, match="gravity"):
            loc.localize(np.zeros((5, 5), np.uint8), queries[0].camera, gravity=bad)
    assert captured == []


def test_up_option_replaces_and_declarations_must_agree(
    small_map: tuple, tmp_path: Path, captured: list
) -> None:
    _, map_images, queries = small_map
    path = tmp_path / "m.db"
    images = map_images[:4]
    build_map(images, path)
    with MapDatabase.open(path, mode="a") as db:
        rep = store_map_gravity(db, WorldDown((0.0, 0.0, -1.0), "option", "up=z"))
        assert rep.source == "option" and rep.g_world == (0.0, 0.0, -1.0)
        # a format's declaration never replaces the user's option
        assert store_map_gravity(db, images[0].world_down).source == "option"
        # up=estimate replaces a stored declaration or option by the estimate
        assert store_map_gravity(db, WorldDown(None, "option", "up=estimate")).source == "estimated"
        assert store_map_gravity(db, WorldDown((0.0, 0.0, -1.0), "option", "up=z")).source == "option"
    loc = Localizer(path)
    loc.localize(read_gray(queries[0].path), queries[0].camera, references=[m.name for m in images])
    for pair in captured[0]["pairs"]:
        assert any(np.allclose(pair.ref_gravity, m.cam_from_world.R @ [0, 0, -1]) for m in images)

    other = tmp_path / "o.db"
    build_map(images, other)  # declared y down
    relabeled = [
        dataclasses.replace(m, world_down=WorldDown((1.0, 0.0, 0.0), "declared", "other")) for m in images
    ]
    with pytest.raises(InputError, match="declare"):
        build_map(relabeled, other)


def test_maps_without_stored_gravity_estimate_it(small_map: tuple, tmp_path: Path) -> None:
    path, _, _ = small_map
    copy = tmp_path / "old.db"
    with sqlite3.connect(path) as src, sqlite3.connect(copy) as dst:
        src.backup(dst)
    with sqlite3.connect(copy) as conn:
        conn.execute("DELETE FROM meta WHERE key IN ('gravity', 'world_down')")
    with MapDatabase.open(copy, mode="r") as db:
        rep = map_gravity(db)
    assert rep.source == "estimated"
    # the office map's robot drives on a level floor: the plane of its centres is level
    assert np.degrees(np.arccos(rep.g_world[1])) < 2.0


def test_gravity_from_truth_is_the_true_gravity_in_the_query_camera(small_map: tuple) -> None:
    _, _, queries = small_map
    g = gravity_from_truth(queries)
    assert set(g) == {q.name for q in queries}
    for q in queries:
        np.testing.assert_allclose(q.cam_from_world.R.T @ g[q.name], [0, 1, 0], atol=1e-12)
    undeclared = dataclasses.replace(queries[0], world_down=None)
    assert gravity_from_truth([undeclared]) == {}
    g_est = gravity_from_truth([undeclared], [0.0, 0.0, 3.0])[undeclared.name]
    np.testing.assert_allclose(undeclared.cam_from_world.R.T @ g_est, [0, 0, 1], atol=1e-12)
