"""Frames with nothing to localize from: a black, uniform or featureless frame is a failed
PoseEstimate with a status and its reason, on every way into the localizer (retrieval, given
references, local structure, bytes, files); an empty or broken image is one InputError."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.features.extract import Features
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, localizer_config
from planarloc.map.builder import build_map


@pytest.fixture(scope="module")
def localizer(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Localizer:
    path = build_map(read_dataset(tiny_world / "map", "tum"), tmp_path_factory.mktemp("map") / "office.db")
    return Localizer(path, localizer_config(structure="tracks"))


def blank_frames(shape: tuple[int, int]) -> dict[str, np.ndarray]:
    h, w = shape
    gradient = np.tile(np.linspace(0, 255, w), (h, 1)).astype(np.uint8)  # not blank to the eye: no corners
    return {
        "black": np.zeros(shape, np.uint8),
        "white": np.full(shape, 255, np.uint8),
        "grey": np.full(shape, 128, np.uint8),
        "gradient": gradient,
        "colour": np.zeros((h, w, 3), np.uint8),
    }


def assert_failed_with_reason(est) -> None:
    assert not est.success and est.pose is None
    assert est.status == "too_few_matches"
    assert "features" in est.message and "featureless" in est.message
    record = est.to_dict()
    json.dumps(record)  # a result record like any other
    assert record["status"] == "too_few_matches" and record["success"] is False


def test_a_featureless_frame_is_a_failed_estimate_with_its_reason(localizer: Localizer) -> None:
    """The issue's IndexError (local structure with zero matches) came with given references."""
    camera = next(iter(localizer.map_cameras))
    references = [p.name for p in localizer.map_images][:4]
    for name, frame in blank_frames((camera.height, camera.width)).items():
        for refs in (None, references):
            est = localizer.localize(frame, camera, references=refs)
            assert_failed_with_reason(est), name
        as_png = cv2.imencode(".png", frame)[1].tobytes()
        assert_failed_with_reason(localizer.localize(as_png))


def test_features_that_match_nothing_fail_without_an_index_error(localizer: Localizer) -> None:
    """Features enough to try, none matching any reference (all descriptors equal: the ratio test
    keeps none): local structure gets zero matches and the query fails with not_in_map."""
    camera = next(iter(localizer.map_cameras))
    n = 20
    features = Features(
        np.random.default_rng(0).uniform(0, 200, (n, 2)).astype(np.float32),
        np.full((n, 128), 128**-0.5, np.float32),
        np.full(n, 2.0, np.float32),
    )
    references = [p.name for p in localizer.map_images][:4]
    est = localizer.localize_features(features, camera, references)
    # no map image sees features that match nothing: the map does not hold the place (issue 32)
    assert not est.success and est.status == "not_in_map" and "tried 4 map images" in est.message
    assert "none of them has 3 or more matches" in est.message


def test_empty_and_broken_images_are_one_input_error(localizer: Localizer, tmp_path: Path) -> None:
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    cut = tmp_path / "cut.png"
    cut.write_bytes(cv2.imencode(".png", np.zeros((240, 320), np.uint8))[1].tobytes()[:60])
    for image, match in [
        (b"", r"query: cannot decode: the image is empty \(0 bytes\)"),
        (bytearray(), "the image is empty"),
        (str(empty), r"empty\.png: cannot read image: the image is empty"),
        (cut, r"cut\.png: cannot read image: truncated PNG"),
        (b"\x89PNG\r\n\x1a\n", "truncated PNG"),
        (b"not an image at all", "not a PNG, JPEG"),
        (np.zeros((0, 320), np.uint8), "empty image"),
    ]:
        with pytest.raises(InputError, match=match):
            localizer.localize(image)
