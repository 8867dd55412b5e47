"""Helpers for the format tests: tiny images and random poses written by the tests themselves."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose


@pytest.fixture
def write_image() -> Callable[..., Path]:
    """``write_image(path, width=8, height=6)``: a small grey PNG (parents created)."""

    def _write(path: Path, width: int = 8, height: int = 6) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(path), np.full((height, width), 128, np.uint8))
        assert ok
        return path

    return _write


@pytest.fixture
def random_poses() -> Callable[[int, int], list[Pose]]:
    """``random_poses(n, seed)``: n random rigid transforms."""

    def _poses(n: int, seed: int = 0) -> list[Pose]:
        rng = np.random.default_rng(seed)
        return [
            Pose(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 3)
            for _ in range(n)
        ]

    return _poses


def assert_pose_close(a: Pose, b: Pose, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(a.R, b.R, atol=atol)
    np.testing.assert_allclose(a.t, b.t, atol=atol)


@pytest.fixture
def pose_close() -> Callable[..., None]:
    return assert_pose_close


def quat_xyzw(pose: Pose) -> np.ndarray:
    w, x, y, z = pose.quat_wxyz
    return np.array([x, y, z, w])


@pytest.fixture
def xyzw() -> Callable[[Pose], np.ndarray]:
    return quat_xyzw
