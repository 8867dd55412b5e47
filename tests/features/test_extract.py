"""SIFT/RootSIFT extraction on generated images."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from textured_images import textured_image

from planarloc.features.extract import (
    DEFAULT_FEATURE_CONFIG,
    FeatureConfig,
    Features,
    extract_features,
    rootsift,
)
from planarloc.geometry.validation import InputError


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return textured_image(np.random.default_rng(0), 240, 320)


def test_rootsift_properties():
    rng = np.random.default_rng(0)
    sift = rng.integers(0, 200, size=(20, 128)).astype(np.float32)
    sift[3] = 0.0
    d = rootsift(sift)
    assert d.dtype == np.float32 and d.shape == (20, 128)
    assert np.all(d >= 0)
    norms = np.linalg.norm(d, axis=1)
    assert np.allclose(np.delete(norms, 3), 1.0, atol=1e-6) and norms[3] == 0.0
    # The dot product of RootSIFT vectors is the Hellinger kernel of the L1-normalised SIFT.
    p = sift[0] / sift[0].sum()
    q = sift[1] / sift[1].sum()
    assert float(d[0] @ d[1]) == pytest.approx(float(np.sqrt(p * q).sum()), rel=1e-5)
    # Invariant to the scale of the input histogram.
    assert np.allclose(rootsift(sift[:1] * 7.0), d[:1], atol=1e-6)
    with pytest.raises(InputError, match="non-negative"):
        rootsift(-sift)


def test_features_on_textured_image(image):
    f = extract_features(image)
    assert isinstance(f, Features)
    n = len(f)
    assert n > 150
    assert f.keypoints.shape == (n, 2) and f.keypoints.dtype == np.float32
    assert f.descriptors.shape == (n, 128) and f.descriptors.dtype == np.float32
    assert f.scales.shape == (n,) and f.scales.dtype == np.float32 and np.all(f.scales > 0)
    assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(f.descriptors >= 0)  # RootSIFT
    assert np.all((f.keypoints >= -0.5) & (f.keypoints <= [image.shape[1] - 0.5, image.shape[0] - 0.5]))


def test_extraction_is_deterministic_and_colour_equals_gray(image):
    a = extract_features(image)
    b = extract_features(np.dstack([image] * 3))
    c = extract_features(image[:, :, None])
    for other in (b, c):
        assert np.array_equal(a.keypoints, other.keypoints)
        assert np.array_equal(a.descriptors, other.descriptors)


def test_max_features_and_plain_sift(image):
    f = extract_features(image, FeatureConfig(max_features=40))
    assert 30 <= len(f) <= 45  # OpenCV keeps ties at the response cut
    g = extract_features(image, FeatureConfig(rootsift=False))
    assert np.allclose(np.linalg.norm(g.descriptors, axis=1), 1.0, atol=1e-5)
    assert not np.allclose(g.descriptors, extract_features(image).descriptors)


def test_keypoints_are_unbiased_across_scales():
    """OpenCV's default SIFT reports keypoints +0.25 px off; with the precise upscale a keypoint
    of a half-size image maps to (x' + 0.5)·2 − 0.5 in the full image without bias."""
    big = textured_image(np.random.default_rng(5), 480, 640)
    small = cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA)
    fb, fs = extract_features(big), extract_features(small)
    sim = fs.descriptors @ fb.descriptors.T
    j = sim.argmax(axis=1)
    mutual = sim.argmax(axis=0)[j] == np.arange(len(fs))
    residual = fb.keypoints[j[mutual]] - ((fs.keypoints[mutual] + 0.5) * 2.0 - 0.5)
    close = np.linalg.norm(residual, axis=1) < 2.0
    assert close.sum() > 50
    assert np.all(np.abs(np.median(residual[close], axis=0)) < 0.1)


def test_tilt_pool_contains_the_plain_features(image):
    plain = extract_features(image)
    tilted = extract_features(image, FeatureConfig(tilt=True))
    n = len(plain)
    assert len(tilted) > 1.5 * n
    assert np.array_equal(tilted.keypoints[:n], plain.keypoints)
    assert np.array_equal(tilted.descriptors[:n], plain.descriptors)
    assert np.all((tilted.keypoints[:, 1] > -1.0) & (tilted.keypoints[:, 1] < image.shape[0]))


def test_blank_image_gives_empty_features():
    f = extract_features(np.full((100, 120), 128, np.uint8))
    assert len(f) == 0
    assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 128) and f.scales.shape == (0,)
    assert len(extract_features(np.full((100, 120), 128, np.uint8), FeatureConfig(tilt=True))) == 0


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((50, 60), np.float32),
        np.zeros((50, 60, 4), np.uint8),
        np.zeros((50,), np.uint8),
        np.zeros((0, 60), np.uint8),
        [[1, 2], [3, 4]],
    ],
)
def test_bad_images_raise(bad):
    with pytest.raises(InputError, match="image"):
        extract_features(bad)


def test_config_defaults_and_validation():
    cfg = DEFAULT_FEATURE_CONFIG
    assert cfg.max_features == 4000 and cfg.tilt is False and cfg.rootsift is True and len(cfg.tilts) == 6
    assert cfg.name == "rootsift-n4000"
    assert FeatureConfig(tilt=True).name == "rootsift-n4000-tilt6"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.max_features = 10  # type: ignore[misc]
    for kwargs in ({"max_features": 0}, {"contrast_threshold": 0.0}, {"tilts": (1.0, 0.7)}, {"sigma": -1.0}):
        with pytest.raises(InputError):
            FeatureConfig(**kwargs)


def test_resize_max_maps_keypoints_back_to_full_resolution() -> None:
    """A 1920x1080 image detected at 960 px: keypoints land where the same structures are in
    full resolution (2x the half-size detections), descriptors stay unit length."""
    from planarloc.features.extract import FeatureConfig, extract_features

    rng = np.random.default_rng(3)
    small = cv2.GaussianBlur((rng.random((540, 960)) * 255).astype(np.uint8), (0, 0), 2.0)
    big = cv2.resize(small, (1920, 1080), interpolation=cv2.INTER_LINEAR)
    f_half = extract_features(small, FeatureConfig(max_features=300, resize_max=None))
    f_big = extract_features(big, FeatureConfig(max_features=300, resize_max=960))
    assert len(f_big.keypoints) > 100
    assert f_big.keypoints[:, 0].max() > 1000 and f_big.keypoints[:, 1].max() > 600  # full-resolution pixels
    expected = (f_half.keypoints + 0.5) * 2.0 - 0.5
    d = np.linalg.norm(f_big.keypoints[:, None] - expected[None], axis=2).min(axis=1)
    assert np.median(d) < 1.5  # same structures (the downscale is not bit-identical to `small`)
    np.testing.assert_allclose(np.linalg.norm(f_big.descriptors, axis=1), 1.0, atol=1e-5)
    # A small image is not resized: identical to resize_max=None.
    a = extract_features(small, FeatureConfig(max_features=300, resize_max=1600))
    np.testing.assert_array_equal(a.keypoints, f_half.keypoints)


def test_resize_max_in_name_and_validation() -> None:
    from planarloc.features.extract import FeatureConfig
    from planarloc.geometry.validation import InputError

    assert FeatureConfig().name == "rootsift-n4000"
    assert FeatureConfig(resize_max=None).name.endswith("-full")
    assert FeatureConfig(resize_max=1024).name.endswith("-r1024")
    with pytest.raises(InputError, match="resize_max"):
        FeatureConfig(resize_max=0)


def test_map_without_resize_max_reads_as_full_resolution() -> None:
    """Maps built before resize_max existed were extracted at full resolution; their queries must be too."""
    import types

    from planarloc.features.extract import FeatureConfig
    from planarloc.map.settings import feature_config_from_map, map_config

    old = types.SimpleNamespace(config={"features": {"max_features": 2000, "tilt": False}})
    assert feature_config_from_map(old).resize_max is None
    new = types.SimpleNamespace(config=map_config(FeatureConfig(resize_max=1024), 64))
    assert feature_config_from_map(new).resize_max == 1024
