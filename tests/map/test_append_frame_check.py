"""Appending images whose world frame is unrelated to the map's (issue #32): the math of
:mod:`planarloc.map.frame_check` on generated geometry, then builds on rendered worlds. The second
half of a trajectory appends silently; the same images with their poses moved by a rigid transform,
or the images of another world, are refused with one line and the map file is left byte for byte
as it was; ``allow_unrelated_frames`` appends them with a warning; a new or empty map is not checked."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.features.extract import DEFAULT_FEATURE_CONFIG, Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.map import builder
from planarloc.map.builder import build_map
from planarloc.map.frame_check import (
    FrameCheckOptions,
    UnrelatedFramesError,
    capped,
    frames_related,
    known_pose_errors_px,
    nearest_first,
    pair_support,
    pair_verdict,
)
from planarloc.map.lock import lock_path_of
from planarloc.map.settings import map_config
from planarloc.map.store import MapDatabase

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
#: a rigid change of world frame: 90° about the vertical and 20 m away
OTHER_FROM_WORLD = Pose(Rotation.from_euler("y", 90, degrees=True).as_matrix(), np.array([20.0, 0.0, 5.0]))


# ---- generated two-view geometry --------------------------------------------------------------
def two_views(
    rng: np.random.Generator, n: int = 200, baseline: float = 1.0
) -> tuple[Pose, np.ndarray, np.ndarray]:
    """``b_from_a`` (b about ``baseline`` m ahead and to the side of a, turned 5°) and (N, 2) pixels of
    N points 3-30 m in front of a that both cameras see."""
    b_from_a = Pose.from_center(
        Rotation.from_euler("y", 5, degrees=True).as_matrix(),
        baseline * np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0),
    )
    pa, pb = [], []
    while len(pa) < n:
        depth = rng.uniform(3.0, 30.0)
        x = np.array([rng.uniform(0, 640), rng.uniform(0, 480)])
        X = np.append(CAMERA.cam_from_img(x[None])[0], 1.0) * depth
        Xb = b_from_a.transform(X[None])[0]
        if Xb[2] <= 0:
            continue
        u = CAMERA.img_from_cam(Xb[None])[0]
        if 0 <= u[0] < 640 and 0 <= u[1] < 480:
            pa.append(x)
            pb.append(u)
    return b_from_a, np.array(pa), np.array(pb)


def rays(px: np.ndarray) -> np.ndarray:
    return CAMERA.bearings_from_img(px)


def test_known_pose_errors_vanish_for_the_true_pose_and_not_for_wrong_ones() -> None:
    rng = np.random.default_rng(0)
    b_from_a, pa, pb = two_views(rng)
    xa, xb = rays(pa), rays(pb)
    f = CAMERA.focal
    assert known_pose_errors_px(b_from_a.R, b_from_a.t, xa, xb, f, f).max() < 1e-6
    # scale is not observable: the same pose with 10 times the baseline explains the matches too
    assert known_pose_errors_px(b_from_a.R, 10 * b_from_a.t, xa, xb, f, f).max() < 1e-6
    # turned by 2° more: every match misses its epipolar line by pixels
    turned = Rotation.from_euler("y", 2, degrees=True).as_matrix() @ b_from_a.R
    assert np.median(known_pose_errors_px(turned, b_from_a.t, xa, xb, f, f)) > 5.0
    # the opposite translation has the same essential matrix (same epipolar lines); the points lie
    # on the wrong half of them (behind a camera), which the error sees
    flipped = known_pose_errors_px(b_from_a.R, -b_from_a.t, xa, xb, f, f)
    assert np.mean(flipped > 6.0) > 0.5


def test_known_pose_errors_without_baseline_are_rotation_transfer() -> None:
    rng = np.random.default_rng(1)
    R = Rotation.from_euler("yx", [8, 2], degrees=True).as_matrix()
    pa = rng.uniform([100, 100], [540, 380], (50, 2))
    xa = rays(pa)
    a = xa @ R.T
    xb = a / a[:, 2:3]
    f = CAMERA.focal
    assert known_pose_errors_px(R, np.zeros(3), xa, xb, f, f).max() < 1e-6
    off = known_pose_errors_px(np.eye(3), np.zeros(3), xa, xb, f, f)
    assert off.min() > 50.0  # 8° of yaw is about 70 px at f = 500
    with pytest.raises(InputError, match="x_b"):
        known_pose_errors_px(R, np.zeros(3), xa, xb[:3], f, f)


def test_pair_support_counts_shared_and_agreeing_matches() -> None:
    rng = np.random.default_rng(2)
    b_from_a, pa, pb = two_views(rng, n=150)
    noisy = pb + rng.normal(0, 0.5, pb.shape)
    outliers = rng.uniform([0, 0], [640, 480], (50, 2))
    pa_all, pb_all = np.vstack([pa, rng.uniform([0, 0], [640, 480], (50, 2))]), np.vstack([noisy, outliers])
    shared, agreeing = pair_support(CAMERA, CAMERA, b_from_a, pa_all, pb_all)
    assert 140 <= shared <= 160 and abs(agreeing - shared) <= 10  # the 150 true matches, few chance ones
    # the same matches under a pose from another world frame: shared as before, few agree
    other = b_from_a @ OTHER_FROM_WORLD
    shared_o, agreeing_o = pair_support(CAMERA, CAMERA, other, pa_all, pb_all)
    assert shared_o == shared and agreeing_o < 0.2 * shared
    assert pair_support(CAMERA, CAMERA, b_from_a, pa[:3], pb[:3]) == (0, 0)


@pytest.mark.parametrize(
    ("shared", "agreeing", "verdict"),
    [
        (10, 10, "unmatched"),
        (29, 29, "unmatched"),
        (30, 24, "agrees"),
        (100, 79, "contradicts"),
        (500, 3, "contradicts"),
    ],
)
def test_pair_verdict(shared: int, agreeing: int, verdict: str) -> None:
    assert pair_verdict(shared, agreeing, FrameCheckOptions(min_shared=30, min_agreement=0.8)) == verdict


@pytest.mark.parametrize(
    ("verdicts", "related"),
    [
        ([], False),
        (["unmatched"] * 40, False),
        (["agrees"], True),
        (["agrees", "unmatched", "unmatched"], True),
        (["agrees", "contradicts"], False),
        (["agrees", "agrees", "contradicts"], True),
        (["contradicts"] * 3, False),
    ],
)
def test_frames_related(verdicts: list[str], related: bool) -> None:
    assert frames_related(verdicts) is related


def test_nearest_first_and_capped() -> None:
    map_centers = np.array([[0.0, 0, 0], [10, 0, 0]])
    centers = np.array([[50.0, 0, 0], [9, 0, 0], [0, 0, 3], [-100, 0, 0]])
    assert nearest_first(centers, map_centers).tolist() == [1, 2, 0, 3]
    assert nearest_first(np.zeros((0, 3)), map_centers).shape == (0,)
    with pytest.raises(InputError, match="at least one map camera"):
        nearest_first(centers, np.zeros((0, 3)))
    rng = np.random.default_rng(3)
    d = rng.random((10, 4)).astype(np.float32)
    f = Features(
        np.arange(20, dtype=np.float32).reshape(10, 2),
        d / np.linalg.norm(d, axis=1, keepdims=True),
        np.ones(10, np.float32),
    )
    assert capped(f, 10) is f
    few = capped(f, 4)
    assert len(few) == 4 and few.keypoints[:, 0].tolist() == [0.0, 6.0, 12.0, 18.0]  # spread: rows 0, 3, 6, 9


@pytest.mark.parametrize(
    "bad",
    [
        {"max_images": 0},
        {"min_shared": 0},
        {"min_agreement": 0.0},
        {"pose_threshold_px": -1.0},
        {"retrieved": -1},
    ],
)
def test_bad_options_are_refused(bad: dict) -> None:
    with pytest.raises(InputError, match="FrameCheckOptions"):
        FrameCheckOptions(**bad)


# ---- builds on rendered worlds ----------------------------------------------------------------
@pytest.fixture(scope="module")
def office(tiny_world: Path) -> list:
    return read_dataset(tiny_world / "map", "tum")


@pytest.fixture(scope="module")
def half_map(office: list, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of the first 6 of the office loop's 12 frames."""
    return build_map(office[:6], tmp_path_factory.mktemp("half") / "half.db", workers=2)


@pytest.fixture
def map_copy(half_map: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "map.db"
    shutil.copyfile(half_map, copy)
    return copy


def moved(images: list) -> list:
    """The same images with their poses in another world frame (``OTHER_FROM_WORLD``)."""
    return [
        dataclasses.replace(im, cam_from_world=im.cam_from_world @ OTHER_FROM_WORLD.inverse())
        for im in images
    ]


def test_second_half_of_the_trajectory_appends_silently(
    office: list, map_copy: Path, caplog: pytest.LogCaptureFixture
) -> None:
    lines: list[str] = []
    with caplog.at_level(logging.INFO, logger="planarloc.map.frame_check"):
        build_map(office[6:], map_copy, workers=2, notify=lines.append)
    assert lines == []
    checks = [r.getMessage() for r in caplog.records if "world frame check" in r.getMessage()]
    assert len(checks) == 1 and "agree with the images' poses" in checks[0]  # it was checked, and agreed
    with MapDatabase.open(map_copy) as db:
        assert db.num_images() == 12 and db.is_complete


@pytest.mark.parametrize("case", ["moved", "another world"])
def test_unrelated_frames_are_refused_and_the_map_is_unchanged(
    case: str, office: list, straight_corridor: Path, map_copy: Path
) -> None:
    images = moved(office[6:]) if case == "moved" else read_dataset(straight_corridor / "map", "tum")
    before = map_copy.read_bytes()
    extracted: list[str] = []

    def count(stage: str, done: int, total: int) -> None:
        extracted.append(stage)

    with pytest.raises(UnrelatedFramesError) as info:
        build_map(images, map_copy, workers=2, progress=count)
    message = str(info.value)
    assert "\n" not in message and message.startswith(
        f"{map_copy}: the {len(images)} new images look unrelated"
    )
    assert "--allow-unrelated-frames" in message
    if case == "moved":
        assert "contradict the images' poses" in message and "0 pair(s) agree" in message
    else:
        assert "no pair shares matches" in message
    assert isinstance(info.value, ValueError)
    assert map_copy.read_bytes() == before  # byte for byte
    assert sorted(p.name for p in map_copy.parent.iterdir()) == [
        "map.db"
    ]  # no lock file, WAL or journal left
    assert "features" not in extracted  # refused before the build's extraction stage


def test_allow_unrelated_frames_appends_with_a_warning(office: list, map_copy: Path) -> None:
    lines: list[str] = []
    build_map(moved(office[6:]), map_copy, workers=2, notify=lines.append, allow_unrelated_frames=True)
    assert len(lines) == 1 and "look unrelated to the map's world frame" in lines[0]
    assert lines[0].endswith("appending them anyway (allow_unrelated_frames)")
    with MapDatabase.open(map_copy) as db:
        assert db.num_images() == 12 and db.is_complete
        np.testing.assert_allclose(
            db.get_pose(office[8].name).center, moved(office)[8].cam_from_world.center, atol=1e-9
        )


def test_features_extracted_by_the_check_are_stored_not_extracted_again(
    office: list, map_copy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    real = builder.extract_image_features

    def counted(image, features):
        calls.append(image.name)
        return real(image, features)

    monkeypatch.setattr(builder, "extract_image_features", counted)
    build_map(office[6:], map_copy, workers=2)
    assert sorted(calls) == sorted(im.name for im in office[6:])  # each new image once


def test_a_new_or_empty_map_is_not_checked(
    office: list, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fail(*args, **kwargs):
        raise AssertionError("the frame check ran")

    monkeypatch.setattr(builder, "check_appended_frames", fail)
    build_map(office[:3], tmp_path / "new.db", workers=2)
    empty = tmp_path / "empty.db"
    MapDatabase.create(empty, map_config(DEFAULT_FEATURE_CONFIG, 64)).close()
    build_map(moved(office[:3]), empty, workers=2)
    build_map(office[:3], tmp_path / "new.db", workers=2)  # resuming a complete map adds nothing: no check
    with MapDatabase.open(empty) as db:
        assert db.num_images() == 3
    assert not lock_path_of(empty).exists()
