"""Tests of planarloc.geometry.essential_decomposition (four decompositions, cheirality)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.epipolar import essential_from_relpose, skew
from planarloc.geometry.essential_decomposition import (
    motion_from_essential,
    relposes_closed_form,
    relposes_from_essential,
)
from planarloc.geometry.validation import InputError


def random_relpose(rng: np.random.Generator, max_angle: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """ref_from_query (R, t) with a rotation of up to max_angle rad and ‖t‖ in [0.3, 2]."""
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0.0, max_angle)).as_matrix()
    t = rng.normal(size=3)
    return R, t * rng.uniform(0.3, 2.0) / np.linalg.norm(t)


def points_in_front(rng, R, t, n, box=10.0, min_depth=0.5):
    """n points of [-box, box]³ (query frame) with depth > min_depth in both cameras."""
    X = np.empty((0, 3))
    while len(X) < n:
        P = rng.uniform(-box, box, size=(4 * n, 3))
        Q = P @ R.T + t
        X = np.vstack([X, P[(P[:, 2] > min_depth) & (Q[:, 2] > min_depth)]])
    X = X[:n]
    Y = X @ R.T + t
    return X / X[:, 2:], Y / Y[:, 2:]


def same_up_to_sign(A, B, tol):
    return min(np.abs(A - B).max(), np.abs(A + B).max()) < tol


@pytest.mark.parametrize("seed", range(5))
def test_motion_from_essential_gives_the_four_decompositions(seed):
    rng = np.random.default_rng(seed)
    for _ in range(20):
        R, t = random_relpose(rng, max_angle=np.pi)
        E = essential_from_relpose(R, t) * rng.uniform(-3, 3)
        Rs, ts = motion_from_essential(E)
        assert Rs.shape == (4, 3, 3) and ts.shape == (4, 3)
        tn = t / np.linalg.norm(t)
        for k in range(4):
            assert np.allclose(Rs[k] @ Rs[k].T, np.eye(3), atol=1e-12)
            assert np.linalg.det(Rs[k]) == pytest.approx(1.0, abs=1e-12)
            assert np.linalg.norm(ts[k]) == pytest.approx(1.0, abs=1e-12)
            # each is a factorisation of E up to scale and sign
            Ek = skew(ts[k]) @ Rs[k]
            assert same_up_to_sign(Ek / np.linalg.norm(Ek), E / np.linalg.norm(E), 1e-12)
        # order: (R1, t), (R1, -t), (R2, t), (R2, -t)
        assert np.allclose(Rs[0], Rs[1]) and np.allclose(Rs[2], Rs[3])
        assert np.allclose(ts[0], -ts[1]) and np.allclose(ts[0], ts[2]) and np.allclose(ts[0], -ts[3])
        # the two rotations are the "twisted pair": R2 = (2 t tᵀ - I) R1
        assert np.allclose(Rs[2], (2 * np.outer(tn, tn) - np.eye(3)) @ Rs[0], atol=1e-12)
        # the truth is among them
        hits = [
            k for k in range(4) if np.allclose(Rs[k], R, atol=1e-12) and np.allclose(ts[k], tn, atol=1e-12)
        ]
        assert len(hits) == 1


def test_motion_from_essential_matches_opencv():
    rng = np.random.default_rng(7)
    for _ in range(20):
        R, t = random_relpose(rng)
        E = essential_from_relpose(R, t)
        Rs, ts = motion_from_essential(E)
        R1, R2, tc = cv2.decomposeEssentialMat(E)
        ours = [Rs[0], Rs[2]]
        for Rc in (R1, R2):
            assert any(np.allclose(Rc, Ro, atol=1e-12) for Ro in ours)
        assert same_up_to_sign(tc.ravel(), ts[0], 1e-12)


def test_motion_from_essential_batched_and_nearest_essential():
    rng = np.random.default_rng(3)
    Es = np.stack([essential_from_relpose(*random_relpose(rng)) for _ in range(6)]).reshape(2, 3, 3, 3)
    Rs, ts = motion_from_essential(Es)
    assert Rs.shape == (2, 3, 4, 3, 3) and ts.shape == (2, 3, 4, 3)
    R0, t0 = motion_from_essential(Es[1, 2])
    assert np.allclose(Rs[1, 2], R0) and np.allclose(ts[1, 2], t0)
    # a slightly perturbed E decomposes like its nearest essential matrix
    R, t = random_relpose(rng)
    E = essential_from_relpose(R, t)
    Rp, tp = motion_from_essential(E + 1e-9 * rng.normal(size=(3, 3)))
    tn = t / np.linalg.norm(t)
    assert any(np.allclose(Rp[k], R, atol=1e-7) and np.allclose(tp[k], tn, atol=1e-7) for k in range(4))


@pytest.mark.parametrize(
    "E, match",
    [
        (np.zeros((3, 3)), "rank < 2"),
        (np.outer([1.0, 2.0, 3.0], [0.0, 1.0, 1.0]), "rank < 2"),
        (np.eye(4), r"expected shape \(\.\.\., 3, 3\)"),
        (np.ones(3), r"expected shape"),
        (np.full((3, 3), np.nan), "NaN or inf"),
    ],
)
def test_motion_from_essential_rejects_bad_input(E, match):
    with pytest.raises(InputError, match=match):
        motion_from_essential(E)
    with pytest.raises(ValueError):
        motion_from_essential(E)


@pytest.mark.parametrize("seed", range(5))
def test_relposes_from_essential_keeps_the_true_pose_only(seed):
    rng = np.random.default_rng(seed)
    for planar in (False, True):
        R, t = random_relpose(rng)
        if planar:
            th = rng.uniform(-1, 1)
            R = Rotation.from_rotvec([0.0, th, 0.0]).as_matrix()
            t = np.array([t[0], 0.0, t[2]])
        xq, xr = points_in_front(rng, R, t, 20)
        E = essential_from_relpose(R, t) * rng.choice([-2.0, 0.5])
        poses = relposes_from_essential(E, xq, xr)
        assert len(poses) == 1
        assert np.allclose(poses[0].R, R, atol=1e-10)
        assert np.allclose(poses[0].t, t / np.linalg.norm(t), atol=1e-10)
        # same result from the closed-form kernel used by the solvers
        fast = relposes_closed_form(E[None], xq, xr)
        assert len(fast) == 1
        assert np.allclose(fast[0].R, poses[0].R, atol=1e-12)
        assert np.allclose(fast[0].t, poses[0].t, atol=1e-12)
        # bearings of any positive length give the same answer
        s = rng.uniform(0.1, 10.0, size=(len(xq), 1))
        poses_b = relposes_from_essential(E, xq * s, xr / s)
        assert len(poses_b) == 1 and np.allclose(poses_b[0].R, R, atol=1e-10)


def test_relposes_from_essential_rejects_inconsistent_cheirality():
    rng = np.random.default_rng(11)
    R, t = random_relpose(rng)
    xq, xr = points_in_front(rng, R, t, 10)
    E = essential_from_relpose(R, t)
    # one point flipped behind the query camera: no decomposition satisfies all points
    xq_bad = xq.copy()
    xq_bad[3] *= -1
    assert relposes_from_essential(E, xq_bad, xr) == []
    assert relposes_closed_form(E[None], xq_bad, xr) == []
    # a point at infinity (parallel rays) fails the test, as documented
    xr_inf = xr.copy()
    d = R @ xq[0]
    xr_inf[0] = d / d[2]
    assert relposes_from_essential(E, xq, xr_inf) == []
    assert relposes_closed_form(E[None], xq, xr_inf) == []
    # zero baseline: every ray pair is parallel
    Y = xq @ R.T
    assert relposes_from_essential(essential_from_relpose(R, t), xq, Y / Y[:, 2:]) == []


def test_relposes_from_essential_validates_input():
    E = essential_from_relpose(np.eye(3), np.array([1.0, 0.0, 0.0]))
    x = np.array([[0.1, 0.2, 1.0], [0.3, -0.1, 1.0]])
    with pytest.raises(InputError, match="same number of rows"):
        relposes_from_essential(E, x, x[:1])
    with pytest.raises(InputError, match=r"expected shape \(N, 3\)"):
        relposes_from_essential(E, x[:, :2], x[:, :2])
    with pytest.raises(InputError, match="zero vector"):
        relposes_from_essential(E, np.vstack([x[:1], np.zeros(3)]), x)
    with pytest.raises(InputError, match="NaN or inf"):
        relposes_from_essential(E, np.vstack([x[:1], [np.inf, 0, 1]]), x)
    with pytest.raises(InputError, match=r"expected shape \(3, 3\)"):
        relposes_from_essential(np.stack([E, E]), x, x)
    with pytest.raises(InputError, match="rank < 2"):
        relposes_from_essential(np.zeros((3, 3)), x, x)
