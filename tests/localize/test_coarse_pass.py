"""The localizer's coarse pass (``LocalizerConfig.coarse_keypoints``): a query localizes from its
first keypoints against as many of each map image's, from all of them only when that fails.

On a rendered world with a RootSIFT map (the base install): an explicit budget is used, its pose is
a promise (error within its std), its matches are recoverable, its local-structure cache is its
own (a later full pass gives exactly what a localizer without a coarse pass gives), and a coarse
pass that fails hands over to the full one, whose answer is the full pass's own."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planarloc.cli.main import main
from planarloc.features.extract import Features, extract_features
from planarloc.features.images import read_gray
from planarloc.features.registry import FEATURE_TYPES
from planarloc.geometry.pose import pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, LocalizerConfig, localizer_config
from planarloc.map.builder import build_map


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    path = tmp_path_factory.mktemp("map") / "office.db"
    build_map(read_dataset(tiny_world / "map", "tum"), path)
    return path, read_dataset(tiny_world / "query", "tum")


def _query_features(loc: Localizer, query) -> Features:
    return extract_features(read_gray(query.path), loc.features)


def test_first_features_are_read_only_views_of_the_leading_rows() -> None:
    rng = np.random.default_rng(0)
    d = rng.standard_normal((10, 8)).astype(np.float32)
    f = Features(rng.uniform(0, 100, (10, 2)).astype(np.float32), d, np.ones(10, np.float32))
    for a in (f.keypoints, f.descriptors, f.scales):
        a.flags.writeable = False
    head = f.first(4)
    assert len(head) == 4
    np.testing.assert_array_equal(head.descriptors, d[:4])
    assert np.shares_memory(head.descriptors, f.descriptors) and not head.descriptors.flags.writeable
    assert f.first(10) is f and f.first(25) is f
    assert len(f.first(0)) == 0
    with pytest.raises(InputError, match="n >= 0"):
        f.first(-1)


@pytest.mark.parametrize("bad", [-1, True, 2.5, "2048"])
def test_a_bad_coarse_budget_is_refused_in_one_line(bad: object) -> None:
    with pytest.raises(InputError, match="coarse_keypoints: expected None or an integer >= 0"):
        LocalizerConfig(coarse_keypoints=bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="coarse_top_n: expected an integer >= 2"):
        LocalizerConfig(coarse_top_n=bad if bad != -1 else 1)  # type: ignore[arg-type]


def test_the_feature_types_default_budget_applies_unless_configured(world_map: tuple) -> None:
    path, _ = world_map
    assert FEATURE_TYPES["rootsift"].coarse_keypoints is None
    assert FEATURE_TYPES["xfeat"].coarse_keypoints == 2048
    assert Localizer(path).coarse_keypoints == 0  # a RootSIFT map: no coarse pass by default
    assert Localizer(path, localizer_config(coarse_keypoints=300)).coarse_keypoints == 300


def test_a_coarse_pose_keeps_its_promise_and_its_matches_can_be_recovered(world_map: tuple) -> None:
    """RootSIFT does not rank its keypoints, so each query's budget is 60 % of its own count (the
    stored order of the map images' is then mostly shared)."""
    path, queries = world_map
    loc = Localizer(path, LocalizerConfig(coarse_keypoints=0))
    used = 0
    for q in queries:
        features = _query_features(loc, q)
        budget = int(0.6 * len(features))
        coarse = loc.with_config(replace(loc.config, coarse_keypoints=budget))
        est, pairs = coarse.localize_pairs(features, q.camera)
        assert est.success, (q.name, est.status, est.message)
        assert est.keypoint_budget == budget and "coarse pass" in est.message
        assert set(est.references) <= set(loc.retrieve(features)[:3])  # the coarse pass's 3 nearest
        used += 1
        for name, pair in zip(est.references, pairs):  # every match is between leading keypoints
            assert pair.query_indices.max() < budget
            stored = loc.db.get_features(name).keypoints.astype(float)
            leading = {tuple(p) for p in stored[:budget]}
            assert all(tuple(p) in leading for p in pair.ref_points)
        t_err, _ = pose_errors(est.pose, q.cam_from_world)
        assert t_err <= 3 * est.position_std_m + 0.05, (q.name, t_err, est.position_std_m)
        again, names = coarse.pairs_for(features, est.references, q.camera, keypoint_budget=budget)
        assert names == est.references
        assert [len(p.query_points) for p in again] == [len(m) for m in est.inliers]
        for a, b in zip(again, pairs):
            np.testing.assert_array_equal(a.query_indices, b.query_indices)
            np.testing.assert_array_equal(a.ref_points, b.ref_points)
    assert used == len(queries)
    # The coarse passes kept their map-image matches apart: the full cache was never filled ...
    assert loc.pair_cache.computed == 0
    # ... so a full pass on the same localizer (shared caches) answers exactly as a fresh one.
    fresh = Localizer(path, LocalizerConfig(coarse_keypoints=0))
    for q in queries:
        a = loc.localize(q.path, q.camera)
        b = fresh.localize(q.path, q.camera)
        assert (a.status, a.keypoint_budget, b.keypoint_budget) == (b.status, 0, 0)
        if a.success:
            np.testing.assert_array_equal(a.pose.t, b.pose.t)
            assert a.position_std_m == b.position_std_m


def test_a_failed_coarse_pass_hands_over_to_every_keypoint(world_map: tuple) -> None:
    """A budget of 5 keypoints cannot match 2 map images (3 matches each at least): the full pass
    answers, exactly as without a coarse pass, and its statistics count both passes."""
    path, queries = world_map
    full = Localizer(path, LocalizerConfig(coarse_keypoints=0))
    tiny = Localizer(path, LocalizerConfig(coarse_keypoints=5))
    q = queries[0]
    features = _query_features(tiny, q)
    est = tiny.localize_features(features, q.camera)
    alone = full.localize_features(features, q.camera)
    assert est.success and alone.success
    assert est.keypoint_budget == 0
    assert "the coarse pass of 5 gave" in est.message
    np.testing.assert_array_equal(est.pose.t, alone.pose.t)
    np.testing.assert_array_equal(est.pose.R, alone.pose.R)
    assert est.stats.time_s["matching"] > 0 and est.stats.iterations >= alone.stats.iterations


def test_the_command_line_takes_and_checks_the_coarse_budget(
    world_map: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, queries = world_map
    assert main(["localize", "--map", str(path), "--coarse-keypoints", "-2", str(queries[0].path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "coarse_keypoints" in err[0] and "-2" in err[0]
    records = tmp_path / "records"
    budget = int(0.6 * len(_query_features(Localizer(path), queries[0])))
    argv = ["localize", "--map", path, "--coarse-keypoints", budget, "--out", tmp_path / "poses.txt"]
    assert main([str(a) for a in [*argv, "--json-dir", records, queries[0].path]]) == 0
    (path_json,) = records.glob("*.json")
    record = json.loads(path_json.read_text())
    assert (
        record["keypoint_budget"] == budget and f"from the {budget} first of the query's" in record["message"]
    )
