"""End to end on a tiny rendered world: map build (resume/append), retrieval, localization."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planarloc.features.images import read_gray
from planarloc.geometry.pose import pose_errors
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.map.builder import build_map
from planarloc.map.store import MapDatabase
from planarloc.robust.options import RansacOptions


@pytest.fixture(scope="module")
def built(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list, list]:
    map_images = read_dataset(tiny_world / "map", "tum")
    queries = read_dataset(tiny_world / "query", "tum")
    path = tmp_path_factory.mktemp("map") / "map.db"
    build_map(map_images, path)
    return path, map_images, queries


@pytest.mark.parametrize("structure", ["none", "tracks"])
def test_queries_are_localized_within_5cm_and_1deg(built: tuple, structure: str) -> None:
    path, _, queries = built
    loc = Localizer(path, LocalizerConfig(ransac=RansacOptions(structure=structure)))
    for q in queries:
        est = loc.localize(read_gray(q.path), q.camera)
        assert est.success, (q.name, est.status, est.message)
        t_err, r_err = pose_errors(est.pose, q.cam_from_world)
        assert t_err < 0.05 and r_err < 1.0, (q.name, t_err, r_err)
        assert len(est.references) >= 2 and est.stats.time_s["end_to_end"] > 0


def test_retrieval_returns_the_nearest_map_images(built: tuple) -> None:
    path, map_images, queries = built
    loc = Localizer(path)
    centers = {m.name: m.cam_from_world.center for m in map_images}
    hits = 0
    for q in queries:
        refs = loc.retrieve(_features(loc, q))
        d = {n: np.linalg.norm(c - q.cam_from_world.center) for n, c in centers.items()}
        nearest = sorted(d, key=d.get)[:5]
        hits += refs[0] in nearest
    assert hits >= len(queries) - 1


def _features(loc: Localizer, q):
    from planarloc.features.extract import extract_features

    return extract_features(read_gray(q.path), loc.features)


def test_live_frame_needs_no_files(built: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path, _, queries = built
    loc = Localizer(path)
    image = read_gray(queries[0].path)
    monkeypatch.chdir(tmp_path)
    est = loc.localize(image, queries[0].camera)
    assert est.success and list(tmp_path.iterdir()) == []


def test_given_references_bypass_retrieval_and_unknown_names_are_errors(built: tuple) -> None:
    path, map_images, queries = built
    loc = Localizer(path)
    image = read_gray(queries[0].path)
    with pytest.raises(ValueError, match="not in the map"):
        loc.localize(image, queries[0].camera, references=["nope.png", map_images[0].name])
    d = sorted(
        map_images, key=lambda m: np.linalg.norm(m.cam_from_world.center - queries[0].cam_from_world.center)
    )
    est = loc.localize(image, queries[0].camera, references=[m.name for m in d[:4]])
    assert est.references == [m.name for m in d[:4]][: len(est.references)]


def test_build_resumes_after_interruption_and_appends(tiny_world: Path, tmp_path: Path) -> None:
    images = read_dataset(tiny_world / "map", "tum")
    path = tmp_path / "m.db"

    class Stop(Exception):
        pass

    def interrupt(stage: str, done: int, total: int) -> None:
        if stage == "features" and done == 4:
            raise Stop

    with pytest.raises(Stop):
        build_map(images[:8], path, progress=interrupt)
    with MapDatabase.open(path) as db:
        assert db.num_images() == 4 and not db.is_complete
    seen = []
    build_map(images[:8], path, progress=lambda s, d, n: seen.append((s, n)))
    assert ("features", 4) in seen  # only the 4 missing images were extracted
    build_map(images, path)  # append the rest
    with MapDatabase.open(path) as db:
        assert db.num_images() == len(images) and db.is_complete
        assert set(db.image_names()) == {im.name for im in images}
    assert Localizer(path).index.dim > 0


def test_map_with_different_features_is_refused(tiny_world: Path, tmp_path: Path) -> None:
    from planarloc.features.extract import FeatureConfig

    images = read_dataset(tiny_world / "map", "tum")[:3]
    path = tmp_path / "m.db"
    build_map(images, path)
    with pytest.raises(ValueError, match="feature config"):
        build_map(images, path, FeatureConfig(max_features=500))
