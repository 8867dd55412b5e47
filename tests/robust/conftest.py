"""Shared fixtures of the robust-estimator tests (generated data only).

Scene generation (``make_scene``) costs far more than one estimate, so scenes are cached per
session and shared between the tests that use the same protocol.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose
from planarloc.synthetic.scenes import SyntheticScene, make_scene


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of ``R_a R_bᵀ`` in degrees, accurate for tiny angles.

    ``arccos((tr - 1) / 2)`` cannot resolve angles below ~1e-6 degrees in double precision
    (1 - cos of 1.7e-8 rad is at the level of machine epsilon), so tests of 1e-6-degree
    accuracy use the rotation vector instead.
    """
    return float(np.degrees(Rotation.from_matrix(R_a @ R_b.T).magnitude()))


def precise_pose_errors(estimate: Pose, truth: Pose) -> tuple[float, float]:
    """(centre error in metres, rotation error in degrees) with :func:`rotation_angle_deg`."""
    return float(np.linalg.norm(estimate.center - truth.center)), rotation_angle_deg(estimate.R, truth.R)


@pytest.fixture(scope="session")
def pose_errors_precise() -> Callable[[Pose, Pose], tuple[float, float]]:
    """:func:`precise_pose_errors` as a fixture (test modules do not import conftest)."""
    return precise_pose_errors


@pytest.fixture(scope="session")
def scene() -> Callable[..., SyntheticScene]:
    """``scene(seed, **make_scene_kwargs)``: a cached :func:`make_scene` with ``default_rng(seed)``.

    The scenes are frozen dataclasses of read-only-by-convention arrays: do not mutate them.
    """
    cache: dict[tuple, SyntheticScene] = {}

    def get(seed: int, **kwargs) -> SyntheticScene:
        key = (seed, tuple(sorted(kwargs.items())))
        if key not in cache:
            cache[key] = make_scene(np.random.default_rng(seed), **kwargs)
        return cache[key]

    return get
