"""2p1p absolute pose (paper Sec. IV-C, eq. 16-18) and the 2D-3D scale of the tracks mode."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from two_view_scenes import unit_relpose

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.solvers.abspose_2p1p import abspose_2p1p, scale_2p1p, scale_from_point3d
from planarloc.synthetic.scenes import random_planar_pose

SEEDS = [0, 1, 2]
EXACT = 1e-8


def tilted_pose(rng: np.random.Generator) -> Pose:
    """A reference that is NOT upright (any rotation, centre off the ground plane)."""
    return Pose.from_center(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-5, 5, 3))


def visible_point(rng: np.random.Generator, *cams: Pose) -> np.ndarray | None:
    """A world point in [-10, 10]³ in front of every camera (depth > 0.5), or None."""
    X = rng.uniform(-10, 10, (256, 3))
    ok = np.ones(len(X), dtype=bool)
    for cam in cams:
        ok &= cam.transform(X)[:, 2] > 0.5
    return X[np.argmax(ok)] if ok.any() else None


def rays(cam: Pose, X: np.ndarray) -> np.ndarray:
    Y = cam.transform(X[None])[0]
    return Y / Y[2]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("ref2_kind", ["planar", "non-planar"])
def test_noise_free_exact_recovery(seed: int, ref2_kind: str) -> None:
    """Also with a NON-planar reference-to-reference transform (eq. 16 assumes nothing)."""
    rng = np.random.default_rng(seed)
    n_checked = 0
    while n_checked < 80:
        query, ref = random_planar_pose(rng), random_planar_pose(rng)
        ref2 = random_planar_pose(rng) if ref2_kind == "planar" else tilted_pose(rng)
        X = visible_point(rng, query, ref2)
        if X is None:
            continue
        rel, rho = unit_relpose(ref, query)
        xq, x2 = rays(query, X), rays(ref2, X)
        out = abspose_2p1p(rel, ref, ref2, xq, x2)
        assert len(out) == 1
        sol = out[0]
        n_checked += 1
        assert np.linalg.norm(sol.pose.R - query.R) < 1e-12
        assert np.linalg.norm(sol.pose.center - query.center) < EXACT
        assert sol.rho == pytest.approx(rho, rel=1e-8)
        assert sol.rho == pytest.approx(np.linalg.norm(query.center - ref.center), rel=1e-8)
        # depths (query, ref2) of the third match: its true depths (z, rays are (x, y, 1)).
        np.testing.assert_allclose(
            sol.depths, [query.transform(X[None])[0, 2], ref2.transform(X[None])[0, 2]], rtol=1e-6
        )
        assert np.all(sol.depths > 0)


@pytest.mark.parametrize("seed", SEEDS)
def test_wrong_sign_of_t_shows_in_pdcheck(seed: int) -> None:
    rng = np.random.default_rng(10 + seed)
    found = 0
    while found < 20:
        query, ref, ref2 = random_planar_pose(rng), random_planar_pose(rng), random_planar_pose(rng)
        X = visible_point(rng, query, ref2)
        if X is None:
            continue
        rel, rho = unit_relpose(ref, query)
        out = abspose_2p1p(Pose(rel.R, -rel.t), ref, ref2, rays(query, X), rays(ref2, X))
        # -t̃ with the same match gives ρ = -ρ_true: the same centre, flagged by Pdcheck.
        assert len(out) == 1
        assert out[0].rho == pytest.approx(-rho, rel=1e-6)
        found += 1


@pytest.mark.parametrize("seed", SEEDS)
def test_collinear_centres_give_no_solution(seed: int) -> None:
    """Query centre on the line through both reference centres: every ρ fits (eq. 18 vanishes)."""
    rng = np.random.default_rng(20 + seed)
    done = 0
    while done < 10:
        c1 = np.array([rng.uniform(-5, 5), 0.0, rng.uniform(-5, 5)])
        a = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(a), 0.0, np.sin(a)])
        ref = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1)
        ref2 = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1 + rng.uniform(1, 5) * d)
        query = Pose.from_center(rotation_from_yaw(rng.uniform(-np.pi, np.pi)), c1 + rng.uniform(-5, 5) * d)
        X = visible_point(rng, query, ref2)
        if X is None:
            continue
        rel, _ = unit_relpose(ref, query)
        assert abspose_2p1p(rel, ref, ref2, rays(query, X), rays(ref2, X)) == []
        done += 1


def test_collinear_centres_with_a_noisy_match_give_no_solution() -> None:
    rng = np.random.default_rng(3)
    ref = Pose.from_center(rotation_from_yaw(0.1), [0.0, 0.0, 0.0])
    ref2 = Pose.from_center(rotation_from_yaw(-0.1), [0.0, 0.0, 4.0])
    query = Pose.from_center(rotation_from_yaw(0.05), [0.0, 0.0, 2.0])  # between the two
    rel, _ = unit_relpose(ref, query)
    X = np.array([1.0, -0.5, 12.0])
    x2 = rays(ref2, X) + np.r_[rng.normal(0.0, 1e-4, 2), 0.0]  # 0.1 px at f = 1000
    out = abspose_2p1p(rel, ref, ref2, rays(query, X), x2)
    # Collinear centres make eq. (18) degenerate whatever the match (a ∥ b): the solver's contract
    # is no solution, never a ρ set by the noise (the old bug gave rho = 4, the centre of ref2).
    assert out == []


def test_zero_relative_translation_gives_no_solution() -> None:
    rng = np.random.default_rng(0)
    ref, ref2 = random_planar_pose(rng), random_planar_pose(rng)
    assert abspose_2p1p(Pose(np.eye(3), np.zeros(3)), ref, ref2, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]) == []


def test_invalid_match_input() -> None:
    rng = np.random.default_rng(0)
    ref, ref2 = random_planar_pose(rng), random_planar_pose(rng)
    rel = Pose(np.eye(3), [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"x_query: expected shape \(3,\)"):
        abspose_2p1p(rel, ref, ref2, [0.0, 1.0], [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="x_ref2: contains NaN"):
        abspose_2p1p(rel, ref, ref2, [0.0, 0.0, 1.0], [np.nan, 0.0, 1.0])


def test_scale_2p1p_kernel_is_eq18() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        a, b, y = rng.normal(size=(3, 3))
        rho_true = rng.uniform(0.1, 10)
        # x₂ on the epipolar plane of translation ρ a + b through y.
        n = np.cross(rho_true * a + b, y)
        x2 = np.cross(n, rng.normal(size=3))
        assert scale_2p1p(a, b, y, x2) == pytest.approx(rho_true, rel=1e-8)
    # Degenerate: a ∥ b and an exact match (x₂ on the epipolar plane of a): every ρ fits.
    a, y = np.array([1.0, 0.0, 0.0]), np.array([0.2, -0.1, 1.0])
    x2 = np.cross(np.cross(a, y), np.array([0.3, 0.4, 0.5]))
    assert np.isnan(scale_2p1p(a, 2.0 * a, y, x2))


@pytest.mark.parametrize("seed", SEEDS)
def test_scale_from_point3d_is_exact(seed: int) -> None:
    rng = np.random.default_rng(30 + seed)
    for _ in range(100):
        query, ref = random_planar_pose(rng), tilted_pose(rng)
        X = visible_point(rng, query, ref)
        if X is None:
            continue
        rel, rho = unit_relpose(ref, query)
        v = rel.R @ rays(query, X)  # query ray in the reference frame
        X_ref = ref.transform(X[None])[0]
        assert scale_from_point3d(rel.t, X_ref, v) == pytest.approx(rho, rel=1e-9)
    # The ray runs along the baseline: no information.
    t = np.array([0.0, 0.0, 1.0])
    assert np.isnan(scale_from_point3d(t, np.array([0.0, 0.0, 5.0]), 2.0 * t))
