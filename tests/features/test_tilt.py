"""Tilt augmentation: image compression, pixel-centre mapping, budgets, and the matching gain."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from textured_images import textured_image

from planarloc.features.extract import FeatureConfig, extract_features
from planarloc.features.matching import match_features
from planarloc.features.tilt import (
    DEFAULT_TILTS,
    check_tilts,
    original_from_tilted,
    tilt_budgets,
    tilt_image,
    tilted_extraction,
    tilted_from_original,
    tilted_height,
)
from planarloc.geometry.validation import InputError


def test_default_tilts_are_the_papers():
    assert np.allclose(DEFAULT_TILTS, [1.0, math.sqrt(2), 2.0, 2 * math.sqrt(2), 4.0, 4 * math.sqrt(2)])
    assert FeatureConfig().tilts == DEFAULT_TILTS


def test_tilt_image_shape_and_identity():
    img = textured_image(np.random.default_rng(0), 377, 200)
    same, s1 = tilt_image(img, 1.0)
    assert s1 == 1.0 and same is img
    for t in DEFAULT_TILTS[1:]:
        tilted, s = tilt_image(img, t)
        assert tilted.shape == (round(377 / t), 200) == (tilted_height(377, t), 200)
        assert tilted.dtype == np.uint8
        assert s == pytest.approx(377 / tilted.shape[0])


def test_pixel_centre_mapping_on_a_blob_centroid():
    """A blob's centroid, measured in each tilted image and mapped back, lands on the original
    centroid; the naive ``y'·t`` mapping misses by about 0.5·(t − 1) px."""
    h, w = 600, 64
    y0, x0 = 301.37, 31.0
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = np.round(250.0 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * 14.0**2))).astype(np.uint8)

    def centroid_y(a: np.ndarray) -> float:
        a = a.astype(float)
        return float((a.sum(axis=1) * np.arange(a.shape[0])).sum() / a.sum())

    c0 = centroid_y(img)
    assert c0 == pytest.approx(y0, abs=0.02)
    for t in DEFAULT_TILTS[1:]:
        tilted, s = tilt_image(img, t)
        yt = centroid_y(tilted)
        mapped = original_from_tilted(np.array([[x0, yt]]), s)[0, 1]
        assert mapped == pytest.approx(c0, abs=0.06), t  # measured < 0.025 px
        if t >= 2:
            assert abs(yt * t - c0) > 0.4 * (t - 1)  # the test does discriminate the conventions


def test_mapping_round_trip_keeps_x():
    pts = np.random.default_rng(1).random((50, 2)) * [640, 480]
    for s in (1.0, 1.4142, 2.8301, 5.6):
        back = original_from_tilted(tilted_from_original(pts, s), s)
        assert np.allclose(back, pts)
        assert np.array_equal(original_from_tilted(pts, s)[:, 0], pts[:, 0])
    assert original_from_tilted(np.array([[10.0, 0.0]]), 2.0)[0, 1] == pytest.approx(0.5)


def test_budgets_proportional_to_area_and_bounded():
    b = tilt_budgets(4000, DEFAULT_TILTS)
    assert b[0] == 4000 and b == sorted(b, reverse=True)
    assert b[2] == 2000 and b[4] == 1000
    assert sum(b) <= 4000 * sum(1 / t for t in DEFAULT_TILTS) + len(b)


def test_check_tilts_rejects_bad_values():
    with pytest.raises(InputError):
        check_tilts([])
    with pytest.raises(InputError, match=">= 1"):
        check_tilts([1.0, 0.5])
    with pytest.raises(InputError):
        check_tilts([1.0, float("nan")])
    with pytest.raises(InputError):
        tilt_image(np.zeros((10, 10), np.uint8), 0.5)


def test_tilted_extraction_maps_keypoints_and_records_tilt():
    img = textured_image(np.random.default_rng(2), 240, 320)
    calls = []

    def detect(image, budget):
        calls.append((image.shape, budget))
        # one "keypoint" at the centre of the (tilted) image
        y = (image.shape[0] - 1) / 2.0
        return np.array([[10.0, y]], np.float32), np.ones((1, 4), np.float32), np.array([3.0], np.float32)

    kp, desc, sizes, index = tilted_extraction(img, detect, 100, (1.0, 2.0, 4.0))
    assert [c[0] for c in calls] == [(240, 320), (120, 320), (60, 320)]
    assert [c[1] for c in calls] == [100, 50, 25]
    assert np.allclose(kp[:, 1], 119.5)  # the image centre row in every tilt
    assert np.array_equal(index, [0, 1, 2]) and desc.shape == (3, 4) and sizes.shape == (3,)


def test_tilt_pool_matches_a_vertically_compressed_view_much_better():
    """Map image = a scene stretched vertically by 2.8 relative to the query (as a tilt under
    planar motion does); the tilted map pool recovers far more correct matches than plain SIFT."""
    rng = np.random.default_rng(3)
    query_img = textured_image(rng, 200, 320)
    s = 2.8
    map_img = cv2.resize(query_img, (320, round(200 * s)), interpolation=cv2.INTER_CUBIC)
    q = extract_features(query_img)
    counts = {}
    for tilt in (False, True):
        r = extract_features(map_img, FeatureConfig(tilt=tilt))
        m = match_features(q, r)
        pred = q.keypoints[m[:, 0]].astype(float)
        pred[:, 1] = (pred[:, 1] + 0.5) * s - 0.5
        err = np.linalg.norm(r.keypoints[m[:, 1]] - pred, axis=1)
        counts[tilt] = int((err < 3.0).sum())
    assert counts[True] >= 100
    assert counts[True] >= 5 * max(counts[False], 1)
