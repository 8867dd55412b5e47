"""The map prior measured from the map's images (planarloc.map.pose_accuracy)."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.so3 import so3_exp
from planarloc.map.pose_accuracy import (
    MIN_POSITION_STD_M,
    MIN_ROTATION_STD_DEG,
    MapPoseAccuracy,
    PairDiscrepancy,
    accuracy_from_discrepancies,
    neighbour_pairs,
    pair_discrepancy,
)

CAMERA = Camera("PINHOLE", 1024, 768, (600.0, 600.0, 512.0, 384.0))


def _corridor(n_images: int, rng: np.random.Generator) -> tuple[list[Pose], np.ndarray]:
    """Poses of a camera driving along +z (1 m apart, yawing a little) and world points ahead of it."""
    poses = []
    for k in range(n_images):
        yaw = 0.05 * np.sin(k)
        R = so3_exp(np.array([0.0, yaw, 0.0]))[0]
        poses.append(Pose.from_center(R, np.array([0.3 * np.sin(0.7 * k), 0.0, float(k)])))
    X = np.column_stack(
        [rng.uniform(-8, 8, 4000), rng.uniform(-3, 3, 4000), rng.uniform(4, 40, 4000) + n_images]
    )
    X[:, 2] -= rng.uniform(0, n_images + 2, 4000)
    return poses, X


def _observe(
    pose: Pose, X: np.ndarray, noise_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the points in front of the camera and inside the image, with noise; and their mask."""
    Xc = X @ pose.R.T + pose.t
    front = Xc[:, 2] > 0.5
    px = np.full((len(X), 2), np.nan)
    px[front] = CAMERA.img_from_cam(Xc[front, :2] / Xc[front, 2:])
    px += rng.normal(0, noise_px, px.shape)
    inside = front & (px[:, 0] > 0) & (px[:, 0] < CAMERA.width) & (px[:, 1] > 0) & (px[:, 1] < CAMERA.height)
    return px, inside


def _perturbed(pose: Pose, rotation_std_rad: float, position_std: float, rng: np.random.Generator) -> Pose:
    R = so3_exp(rng.normal(0, rotation_std_rad, 3))[0] @ pose.R
    return Pose.from_center(R, pose.center + rng.normal(0, position_std, 3))


def _measure(
    rotation_std_deg: float, position_std: float, seed: int, noise_px: float = 0.3
) -> MapPoseAccuracy:
    rng = np.random.default_rng(seed)
    truth, X = _corridor(14, rng)
    claimed = [_perturbed(p, np.radians(rotation_std_deg), position_std, rng) for p in truth]
    found = []
    for i, j in neighbour_pairs(np.array([p.center for p in claimed])):
        pa, ina = _observe(truth[i], X, noise_px, rng)
        pb, inb = _observe(truth[j], X, noise_px, rng)
        both = ina & inb
        d = pair_discrepancy(CAMERA, CAMERA, claimed[j] @ claimed[i].inverse(), pa[both], pb[both])
        assert d is not None
        found.append(d)
    accuracy = accuracy_from_discrepancies(found)
    assert accuracy is not None
    return accuracy


def test_exact_poses_measure_at_keypoint_noise_level_and_the_noise_is_recovered():
    # The relative poses of 0.3 px matches are good to ~0.003° (rotation) and ~0.03° (direction,
    # 1 m baselines): exact map poses must measure at that level, not at the 0.1° / 2 cm default.
    accuracy = _measure(0.0, 0.0, seed=1)
    assert MIN_ROTATION_STD_DEG <= accuracy.rotation_std_deg <= 0.02
    assert MIN_POSITION_STD_M <= accuracy.position_std_m <= 0.005
    assert accuracy.keypoint_std_px == pytest.approx(0.3, rel=0.25)


@pytest.mark.parametrize("rotation_std_deg, position_std", [(0.2, 0.0), (0.0, 0.05), (0.3, 0.1)])
def test_perturbed_poses_are_measured_within_a_factor_of_two(rotation_std_deg, position_std):
    accuracy = _measure(rotation_std_deg, position_std, seed=2)
    if rotation_std_deg:
        assert rotation_std_deg / 2 <= accuracy.rotation_std_deg <= 2 * rotation_std_deg
    else:
        assert accuracy.rotation_std_deg < 0.05
    if position_std:
        assert position_std / 2 <= accuracy.position_std_m <= 2 * position_std
    else:
        assert accuracy.position_std_m < 0.01


def test_a_wrong_pair_does_not_move_the_estimate():
    rng = np.random.default_rng(3)
    truth, X = _corridor(10, rng)
    found = []
    for i, j in neighbour_pairs(np.array([p.center for p in truth])):
        pa, ina = _observe(truth[i], X, 0.3, rng)
        pb, inb = _observe(truth[j], X, 0.3, rng)
        both = ina & inb
        found.append(pair_discrepancy(CAMERA, CAMERA, truth[j] @ truth[i].inverse(), pa[both], pb[both]))
    clean = accuracy_from_discrepancies(found)
    bad = found[0]
    wrong = PairDiscrepancy(
        bad.delta + np.array([0.2, 0.0, 0.0, 0.3, 0.0]), bad.cov, bad.baseline_m, bad.inliers, bad.residual_px
    )
    assert accuracy_from_discrepancies([wrong, *found[1:]]) == clean


def test_too_few_pairs_or_matches_measure_nothing():
    assert accuracy_from_discrepancies([]) is None
    pose = Pose.from_center(np.eye(3), np.array([0.0, 0.0, 1.0]))
    assert pair_discrepancy(CAMERA, CAMERA, pose, np.zeros((10, 2)), np.zeros((10, 2))) is None


def test_neighbour_pairs_skip_repeated_centres_and_are_capped():
    centers = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
    pairs = neighbour_pairs(centers)
    assert (0, 1) not in pairs and all(i < j for i, j in pairs)
    many = neighbour_pairs(np.column_stack([np.arange(500.0), np.zeros(500), np.zeros(500)]), max_pairs=20)
    assert len(many) == 20


def test_json_round_trip():
    a = MapPoseAccuracy(0.04, 0.015, 14, 0.36)
    assert MapPoseAccuracy.from_json(a.to_json()) == a
    assert "0.04°" in a.summary() and "14 image pairs" in a.summary()
