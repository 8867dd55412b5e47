"""Local optimisation of absolute-pose hypotheses (robust/local_optimization.py).

The planar stage must move only within the planar model (yaw, centre in the references'
level plane) and reach the truth from a perturbed planar hypothesis; it must not run for a
hypothesis that is not level with the references, nor when they are not level with each
other; the 6DoF stage must recover a tilt the planar stage cannot. ``distinct_centres`` is the
centre test that picks near-ties for local optimisation.
"""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.robust.local_optimization import (
    LocalOptimization,
    distinct_centres,
    level_plane,
    refine_planar_then_6dof,
)
from planarloc.robust.problem import build_problem
from planarloc.robust.refinement import RefineSettings
from planarloc.synthetic.scenes import make_scene

TH_SQ = 36.0  # 3τ at τ = 2 px
COS_LEVEL = np.cos(np.radians(1.5))


def _rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])


def _scene(seed: int, **kw):
    sc = make_scene(np.random.default_rng(seed), num_refs=3, matches_per_pair=30, noise_px=0.0, **kw)
    return sc, build_problem(sc.query_camera, sc.pairs)


def _lo(p, R, t, level, planar_iterations: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    lo = LocalOptimization(
        RefineSettings(TH_SQ, 2.0, iterations, 0.5, 0.0, 0.0), planar_iterations, level, COS_LEVEL, 128
    )
    return refine_planar_then_6dof(np.ascontiguousarray(R), np.ascontiguousarray(t), p.arrays, lo)


def _planar_perturbed(sc, yaw_deg: float, shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The true query pose with extra yaw and a centre shift in the level plane (y = 0)."""
    R = sc.query_pose.R @ rotation_from_yaw(np.radians(yaw_deg))
    c = sc.query_pose.center + np.array([shift[0], 0.0, shift[1]])
    return R, -R @ c


def test_level_plane_is_an_orthonormal_basis_around_the_common_y_axis() -> None:
    _, p = _scene(0)
    B = level_plane(p.ref_R, COS_LEVEL)
    np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(B[:, 1], p.ref_R[0, 1], atol=1e-12)  # synthetic references: y = world y


def test_level_plane_is_empty_when_references_are_not_level_with_each_other() -> None:
    _, p = _scene(0)
    ref_R = p.ref_R.copy()
    ref_R[1] = _rot_x(5.0) @ ref_R[1]  # one reference pitched by 5°
    assert level_plane(ref_R, COS_LEVEL).shape == (0, 3)
    assert level_plane(ref_R, np.cos(np.radians(10.0))).shape == (3, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planar_stage_moves_only_within_the_plane_and_reaches_the_truth(seed: int) -> None:
    sc, p = _scene(seed)
    R0, t0 = _planar_perturbed(sc, 1.0, (0.15, -0.1))
    R, t = _lo(p, R0, t0, level_plane(p.ref_R, COS_LEVEL), 6, 0)
    c = -R.T @ t
    np.testing.assert_allclose(R[1], R0[1], atol=1e-12)  # camera y axis (tilt) untouched
    assert abs(c[1] - (-R0.T @ t0)[1]) < 1e-12  # height untouched
    assert np.linalg.norm(c - sc.query_pose.center) < 1e-4
    assert np.degrees(np.arccos(np.clip((np.trace(R @ sc.query_pose.R.T) - 1) / 2, -1, 1))) < 1e-3


def test_planar_stage_is_skipped_for_a_hypothesis_not_level_with_the_references() -> None:
    sc, p = _scene(3)
    R0, t0 = _planar_perturbed(sc, 1.0, (0.15, -0.1))
    R0 = _rot_x(3.0) @ R0  # tilted beyond the 1.5° tolerance
    R, t = _lo(p, R0, t0, level_plane(p.ref_R, COS_LEVEL), 6, 0)
    np.testing.assert_array_equal(R, R0)
    np.testing.assert_array_equal(t, t0)
    R, t = _lo(p, *_planar_perturbed(sc, 1.0, (0.15, -0.1)), np.zeros((0, 3)), 6, 0)  # no level plane
    np.testing.assert_array_equal(R, _planar_perturbed(sc, 1.0, (0.15, -0.1))[0])


def test_6dof_stage_recovers_a_tilt_the_planar_stage_cannot() -> None:
    sc, p = _scene(4, query_tilt_deg=1.0)  # the true query has random pitch and roll
    level = level_plane(p.ref_R, COS_LEVEL)
    R_true = sc.query_pose.R
    tilt = np.degrees(np.arccos(R_true[1] @ level[:, 1]))
    assert tilt > 0.5  # this seed: a tilt the planar stage cannot absorb
    R0 = R_true @ _align(R_true[1], level[:, 1])  # the truth with its tilt removed: level
    t0 = -R0 @ sc.query_pose.center
    err = lambda R: np.degrees(np.arccos(np.clip((np.trace(R @ R_true.T) - 1) / 2, -1, 1)))  # noqa: E731
    planar, full = _lo(p, R0, t0, level, 4, 0)[0], _lo(p, R0, t0, level, 4, 6)[0]
    assert err(planar) > 0.9 * tilt
    assert err(full) < 1e-3


def _align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues)."""
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-15:
        return np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def test_distinct_centres_uses_a_tenth_of_the_distance_to_the_nearest_reference() -> None:
    refs = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, -20.0]])  # nearest reference 10 m from the origin
    cb = np.zeros(3)
    R = np.tile(np.eye(3), (3, 1, 1))
    centres = np.array([[0.0, 0.0, 0.0], [0.9, 0.0, 0.0], [1.1, 0.0, 0.0]])
    t = -centres  # R = I: t = -c
    np.testing.assert_array_equal(distinct_centres(R, t, cb, refs), [False, False, True])
