"""2p2p absolute pose (paper Sec. IV-B, eq. 12-15): Rcheck, triangulated scales, Pdcheck."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from two_view_scenes import unit_relpose

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.solvers.abspose_2p2p import abspose_2p2p, triangulate_scales
from planarloc.synthetic.scenes import random_planar_pose

SEEDS = [0, 1, 2]
EXACT = 1e-8


def assert_pose_close(a: Pose, b: Pose, tol: float = EXACT) -> None:
    assert np.linalg.norm(a.R - b.R) < tol
    assert np.linalg.norm(a.center - b.center) < tol * max(1.0, float(np.linalg.norm(b.center)))


def random_general_pose(rng: np.random.Generator) -> Pose:
    return Pose.from_center(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-5, 5, 3))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("planar", [True, False], ids=["planar", "general"])
def test_noise_free_exact_recovery(seed: int, planar: bool) -> None:
    rng = np.random.default_rng(seed)
    make = random_planar_pose if planar else random_general_pose
    n_checked = 0
    for _ in range(120):
        query, ref, ref2 = make(rng), make(rng), make(rng)
        rel, rho = unit_relpose(ref, query)
        rel2, rho2 = unit_relpose(ref2, query)
        out = abspose_2p2p(rel, rel2, ref, ref2)
        if out.sin_parallax < 1e-3:  # nearly collinear centres: ill-conditioned, tested below
            continue
        n_checked += 1
        assert not out.regularised
        assert_pose_close(out.pose, query)
        assert out.rho == pytest.approx(rho, rel=EXACT)
        assert out.rho2 == pytest.approx(rho2, rel=EXACT)
        assert out.rho == pytest.approx(np.linalg.norm(query.center - ref.center), rel=EXACT)
        assert out.rho2 == pytest.approx(np.linalg.norm(query.center - ref2.center), rel=EXACT)
        assert out.rcheck_deg < 1e-5  # arccos near 1: ~1e-6 degree resolution
        expected_sin = np.linalg.norm(np.cross(rel.t, rel.R @ rel2.R.T @ rel2.t))
        assert out.sin_parallax == pytest.approx(expected_sin, abs=1e-12)
    assert n_checked > 100


@pytest.mark.parametrize("seed", SEEDS)
def test_non_unit_translations_are_normalised(seed: int) -> None:
    rng = np.random.default_rng(10 + seed)
    query, ref, ref2 = random_planar_pose(rng), random_planar_pose(rng), random_planar_pose(rng)
    rel, rho = unit_relpose(ref, query)
    rel2, rho2 = unit_relpose(ref2, query)
    out = abspose_2p2p(Pose(rel.R, 3.0 * rel.t), Pose(rel2.R, 0.2 * rel2.t), ref, ref2)
    assert_pose_close(out.pose, query, 1e-7)
    assert out.rho == pytest.approx(rho, rel=1e-7)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("which", [1, 2])
def test_rcheck_equals_the_injected_rotation_error(seed: int, which: int) -> None:
    rng = np.random.default_rng(20 + seed)
    query, ref, ref2 = random_planar_pose(rng), random_planar_pose(rng), random_planar_pose(rng)
    rel, _ = unit_relpose(ref, query)
    rel2, _ = unit_relpose(ref2, query)
    for angle_deg in [0.5, 2.0, 10.0, 45.0]:
        axis = rng.normal(size=3)
        dR = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
        # A rotation error dR in one relative pose: R R₂ᵀ differs from R₁₂ by exactly dR.
        bad1 = Pose(dR @ rel.R, rel.t) if which == 1 else rel
        bad2 = Pose(dR @ rel2.R, rel2.t) if which == 2 else rel2
        out = abspose_2p2p(bad1, bad2, ref, ref2)
        assert out.rcheck_deg == pytest.approx(angle_deg, abs=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_pdcheck_signs(seed: int) -> None:
    """The wrong sign of a relative translation (a cheirality mistake) shows as a negative scale."""
    rng = np.random.default_rng(30 + seed)
    done = 0
    while done < 20:
        query, ref, ref2 = random_planar_pose(rng), random_planar_pose(rng), random_planar_pose(rng)
        rel, rho = unit_relpose(ref, query)
        rel2, rho2 = unit_relpose(ref2, query)
        if abspose_2p2p(rel, rel2, ref, ref2).sin_parallax < 0.05:
            continue
        done += 1
        flip1 = abspose_2p2p(Pose(rel.R, -rel.t), rel2, ref, ref2)
        assert flip1.rho == pytest.approx(-rho, rel=1e-8) and flip1.rho2 == pytest.approx(rho2, rel=1e-8)
        flip2 = abspose_2p2p(rel, Pose(rel2.R, -rel2.t), ref, ref2)
        assert flip2.rho == pytest.approx(rho, rel=1e-8) and flip2.rho2 == pytest.approx(-rho2, rel=1e-8)
        both = abspose_2p2p(Pose(rel.R, -rel.t), Pose(rel2.R, -rel2.t), ref, ref2)
        assert both.rho < 0 and both.rho2 < 0


@pytest.mark.parametrize("seed", SEEDS)
def test_collinear_centres_use_the_regularised_branch(seed: int) -> None:
    """Query on the line through both reference centres: CᵀC is singular (eq. 15)."""
    rng = np.random.default_rng(40 + seed)
    c1 = np.array([rng.uniform(-5, 5), 0.0, rng.uniform(-5, 5)])
    d = np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), 0.0, np.sin(a)])
    for s_query, s_ref2 in [(2.0, 5.0), (-3.0, 4.0), (6.0, 1.5)]:
        ref = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1)
        ref2 = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1 + s_ref2 * d)
        query = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1 + s_query * d)
        rel, _ = unit_relpose(ref, query)
        rel2, _ = unit_relpose(ref2, query)
        out = abspose_2p2p(rel, rel2, ref, ref2)
        assert out.regularised
        assert out.sin_parallax < 1e-6
        assert out.rcheck_deg < 1e-5  # the rotation is still right
        np.testing.assert_allclose(out.pose.R, query.R, atol=1e-12)


def test_zero_relative_translation_is_rejected() -> None:
    rng = np.random.default_rng(0)
    ref, ref2 = random_planar_pose(rng), random_planar_pose(rng)
    with pytest.raises(ValueError, match="non-zero"):
        abspose_2p2p(Pose(np.eye(3), np.zeros(3)), Pose(np.eye(3), [1.0, 0.0, 0.0]), ref, ref2)


def test_triangulate_scales_kernel() -> None:
    t1 = np.array([1.0, 0.0, 0.0])
    t2 = np.array([0.0, 0.0, 1.0])
    b = 2.0 * t1 - 3.0 * t2  # ρ = 2, ρ₂ = 3
    rho, rho2, reg = triangulate_scales(t1, t2, b)
    assert (rho, rho2, reg) == (pytest.approx(2.0), pytest.approx(3.0), False)
    rho, rho2, reg = triangulate_scales(t1, t1, 2.0 * t1)
    assert reg  # parallel: (CᵀC + I)⁻¹ Cᵀ b
    C = np.c_[t1, -t1]
    expected = np.linalg.solve(C.T @ C + np.eye(2), C.T @ (2.0 * t1))
    np.testing.assert_allclose([rho, rho2], expected, atol=1e-12)
