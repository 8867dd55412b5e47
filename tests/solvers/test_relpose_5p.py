"""Tests of the five-point solvers (Nistér 2004 and Stewénius et al. 2006).

Generated data only. PoseLib is the peer-library oracle (its convention x2 = R x1 + t is
ours with x1 = query, x2 = reference; it expects unit bearings).
"""

from __future__ import annotations

import numpy as np
import poselib
import pytest
from two_view_scenes import e_distance, make_scene, pose_error, random_relpose, unit

from planarloc.geometry.epipolar import essential_from_relpose, triangulation_depths
from planarloc.geometry.validation import InputError
from planarloc.solvers import (
    essentials_5p_nister,
    essentials_5p_stewenius,
    relpose_5p_nister,
    relpose_5p_nister_batch,
    relpose_5p_stewenius,
    relpose_5p_stewenius_batch,
)
from planarloc.solvers._five_point import MONOMIALS, five_point_constraints

SOLVERS = {
    "nister": (essentials_5p_nister, relpose_5p_nister, relpose_5p_nister_batch),
    "stewenius": (essentials_5p_stewenius, relpose_5p_stewenius, relpose_5p_stewenius_batch),
}


def best_error(poses, R, t):
    return min((pose_error(p, R, t) for p in poses), default=np.inf)


def sets_agree(As, Bs, tol):
    return len(As) == len(Bs) and all(min(e_distance(a, b) for b in Bs) < tol for a in As)


# ---- exact recovery -------------------------------------------------------------------------


@pytest.mark.parametrize("name", SOLVERS)
@pytest.mark.parametrize("planar", [False, True], ids=["6dof", "planar"])
@pytest.mark.parametrize("seed", range(3))
def test_exact_recovery(name, planar, seed):
    essentials, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(100 * seed + planar)
    for _ in range(60):
        xq, xr, R, t = make_scene(rng, planar=planar)
        poses = relpose(xq, xr)
        assert best_error(poses, R, t) < 1e-8
        Es = essentials(xq, xr)
        assert 1 <= len(Es) <= 10 and len(poses) <= len(Es)
        assert min(e_distance(E, essential_from_relpose(R, t)) for E in Es) < 1e-8
        for E in Es:  # every returned matrix is an exact essential matrix of the data
            assert np.abs(np.einsum("ni,ij,nj->n", unit(xr), E, unit(xq))).max() < 1e-9
            s = np.linalg.svd(E, compute_uv=False)
            assert s[0] - s[1] < 1e-8 and s[2] < 1e-8


@pytest.mark.parametrize("name", SOLVERS)
def test_bearings_all_around(name):
    """Bearings of any length and any direction (points behind the 'image plane' too)."""
    _, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(5)
    for _ in range(40):
        R, t = random_relpose(rng, max_angle=np.pi)
        X = rng.uniform(-10, 10, size=(5, 3))
        Y = X @ R.T + t
        if min(np.linalg.norm(X, axis=1).min(), np.linalg.norm(Y, axis=1).min()) < 0.5:
            continue
        xq = unit(X) * rng.uniform(0.1, 10, size=(5, 1))
        xr = unit(Y) * rng.uniform(0.1, 10, size=(5, 1))
        assert best_error(relpose(xq, xr), R, t / np.linalg.norm(t)) < 1e-8


@pytest.mark.parametrize("name", SOLVERS)
def test_extra_points_used_for_cheirality(name):
    _, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(6)
    for _ in range(30):
        xq, xr, R, t = make_scene(rng, n=20)
        minimal = relpose(xq[:5], xr[:5])
        poses = relpose(xq, xr)
        assert best_error(poses, R, t) < 1e-8
        assert len(poses) <= len(minimal)
        for p in poses:  # every returned pose passes cheirality on all 20 points
            assert np.all(triangulation_depths(p.R, p.t, xq, xr) > 0)


@pytest.mark.parametrize("name", SOLVERS)
def test_planar_structure_is_not_degenerate(name):
    """Five coplanar points (plane not through the camera centres) still give the truth."""
    _, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(8)
    done = 0
    while done < 30:
        R, t = random_relpose(rng)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        if n[2] < 0.3 or abs(n @ (-R.T @ t) - 5.0) < 0.5:
            continue  # the plane n·X = 5 must face the cameras and miss the reference centre
        P = rng.uniform(-10, 10, size=(200, 3))
        P = P - np.outer(P @ n - 5.0, n)
        P = P[(P[:, 2] > 0.5) & ((P @ R.T + t)[:, 2] > 0.5)]
        if len(P) < 5:
            continue
        done += 1
        X = P[:5]
        Y = X @ R.T + t
        poses = relpose(X / X[:, 2:], Y / Y[:, 2:])
        assert best_error(poses, R, t / np.linalg.norm(t)) < 1e-7


@pytest.mark.parametrize("name", SOLVERS)
def test_small_noise_near_exact(name):
    _, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(9)
    errors = []
    for _ in range(100):
        xq, xr, R, t = make_scene(rng, n=5, noise=1e-9)
        errors.append(best_error(relpose(xq, xr), R, t))
    errors = np.array(errors)
    # minimal solvers amplify noise by the (random) conditioning of the sample
    assert np.median(errors) < 1e-7
    assert np.quantile(errors, 0.9) < 1e-5


# ---- degenerate and invalid input ----------------------------------------------------------------


def degenerate_samples():
    rng = np.random.default_rng(10)
    xq, xr, R, t = make_scene(rng)
    out = {}
    a, b = xq.copy(), xr.copy()
    a[3], b[3] = a[1], b[1]
    out["repeated point"] = (a, b)
    out["all points identical"] = (np.repeat(xq[:1], 5, axis=0), np.repeat(xr[:1], 5, axis=0))
    Y = (xq * rng.uniform(1, 10, size=(5, 1))) @ R.T  # zero baseline
    out["pure rotation"] = (xq, Y / Y[:, 2:])
    out["points at infinity"] = (xq, (xq @ R.T) * rng.uniform(0.5, 2, size=(5, 1)))
    # all points on one epipolar plane (coplanar with both camera centres)
    c_ref = -R.T @ t  # reference centre in the query frame
    u = rng.normal(size=3)
    X = np.array([rng.uniform(1, 5) * c_ref + rng.uniform(-3, 3) * u + np.array([0, 0, rng.uniform(4.0, 8.0)])
                  for _ in range(5)])  # fmt: skip
    normal = np.cross(c_ref, X[0])
    X = X - np.outer((X @ normal) / (normal @ normal), normal)  # project onto the plane (0, c_ref, X0)
    Y = X @ R.T + t
    out["one epipolar plane"] = (X / X[:, 2:], Y / Y[:, 2:])
    return out


DEGENERATE = degenerate_samples()


@pytest.mark.parametrize("name", SOLVERS)
@pytest.mark.parametrize("case", DEGENERATE)
def test_degenerate_input_gives_no_solution(name, case):
    essentials, relpose, batch = SOLVERS[name]
    xq, xr = DEGENERATE[case]
    assert essentials(xq, xr) == []
    assert relpose(xq, xr) == []
    R, t, valid = batch(xq[None], xr[None])
    assert not valid.any() and np.isnan(R).all() and np.isnan(t).all()


@pytest.mark.parametrize("name", SOLVERS)
def test_invalid_input_raises(name):
    essentials, relpose, batch = SOLVERS[name]
    rng = np.random.default_rng(12)
    xq, xr, _, _ = make_scene(rng, n=6)
    with pytest.raises(InputError, match=r"expected shape \(5, 3\)"):
        essentials(xq, xr)  # the minimal solve takes exactly five
    with pytest.raises(InputError, match="at least 5 rows"):
        relpose(xq[:4], xr[:4])
    with pytest.raises(InputError, match=r"expected shape \(N, 3\)"):
        relpose(xq[:, :2], xr[:, :2])
    with pytest.raises(InputError, match="same number of rows"):
        relpose(xq, xr[:5])
    bad = xq.copy()
    bad[2, 0] = np.nan
    with pytest.raises(InputError, match=r"NaN or inf \(first at index \(2, 0\)\)"):
        relpose(bad, xr)
    bad[2, 0] = np.inf
    with pytest.raises(ValueError):
        essentials(bad[:5], xr[:5])
    bad = xq.copy()
    bad[4] = 0.0
    with pytest.raises(InputError, match=r"x_query\[4\] is a zero vector"):
        relpose(bad, xr)
    with pytest.raises(InputError, match=r"expected shape \(N, 5, 3\)"):
        batch(xq[None], xr[None])
    with pytest.raises(InputError, match="same shape"):
        batch(np.stack([xq[:5]] * 2), xr[None, :5])
    with pytest.raises(InputError, match="zero vector"):
        batch(np.zeros((1, 5, 3)), xr[None, :5])
    with pytest.raises(InputError, match="NaN or inf"):
        batch(np.full((1, 5, 3), np.nan), xr[None, :5])


# ---- batched API --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SOLVERS)
def test_batch_matches_single_calls(name):
    _, relpose, batch = SOLVERS[name]
    rng = np.random.default_rng(13)
    scenes = [make_scene(rng, planar=bool(i % 2)) for i in range(60)]
    XQ = np.stack([s[0] for s in scenes])
    XR = np.stack([s[1] for s in scenes])
    XQ[7], XR[7] = DEGENERATE["repeated point"]
    XQ[20], XR[20] = DEGENERATE["pure rotation"]
    R, t, valid = batch(XQ, XR)
    assert R.shape == (60, 10, 3, 3) and t.shape == (60, 10, 3) and valid.shape == (60, 10)
    assert valid.dtype == bool
    assert not valid[7].any() and not valid[20].any()
    for m in range(60):
        k = int(valid[m].sum())
        assert valid[m, :k].all()  # packed first
        assert np.isnan(R[m, k:]).all() and np.isnan(t[m, k:]).all()
        single = relpose(XQ[m], XR[m])
        assert len(single) == k
        for p in single:  # same poses (the batch polishes roots a little less)
            assert min(max(np.abs(R[m, j] - p.R).max(), np.abs(t[m, j] - p.t).max()) for j in range(k)) < 1e-6
        if m not in (7, 20):
            Rt, tt = scenes[m][2], scenes[m][3]
            assert min(max(np.abs(R[m, j] - Rt).max(), np.abs(t[m, j] - tt).max()) for j in range(k)) < 1e-6
    # rotations are proper and translations unit
    Rv, tv = R[valid], t[valid]
    assert np.allclose(Rv @ Rv.transpose(0, 2, 1), np.eye(3), atol=1e-10)
    assert np.allclose(np.linalg.det(Rv), 1.0) and np.allclose(np.linalg.norm(tv, axis=1), 1.0)
    # an empty batch is fine
    R0, t0, v0 = batch(np.empty((0, 5, 3)), np.empty((0, 5, 3)))
    assert R0.shape == (0, 10, 3, 3) and v0.shape == (0, 10)


@pytest.mark.parametrize("name", SOLVERS)
def test_parallel_batch_equals_serial(name):
    _, _, batch = SOLVERS[name]
    rng = np.random.default_rng(19)
    scenes = [make_scene(rng) for _ in range(40)]
    XQ = np.stack([s[0] for s in scenes])
    XR = np.stack([s[1] for s in scenes])
    R, t, valid = batch(XQ, XR)
    Rp, tp, validp = batch(XQ, XR, parallel=True)
    assert np.array_equal(valid, validp)
    assert np.array_equal(R[valid], Rp[valid]) and np.array_equal(t[valid], tp[valid])


# ---- cross-checks -------------------------------------------------------------------------------


def essential_residual(E):
    """max |2 E Eᵀ E − tr(E Eᵀ) E| of the unit-norm E: how exactly E is essential."""
    E = E / np.linalg.norm(E)
    EEt = E @ E.T
    return np.abs(2 * EEt @ E - np.trace(EEt) * E).max()


@pytest.mark.parametrize("name", SOLVERS)
@pytest.mark.parametrize("planar", [False, True], ids=["6dof", "planar"])
def test_agrees_with_poselib(name, planar):
    """Same essential matrices and poses as PoseLib, up to scale and sign.

    PoseLib (also Nistér's method) loses digits on ill-conditioned samples: some of its
    matrices are essential only to 1e-3. Only its accurate solutions (essential to 1e-10, poses
    fitting the five epipolar constraints to 1e-11) must be matched by ours; ours are all exact
    (checked in test_exact_recovery).
    """
    essentials, relpose, _ = SOLVERS[name]
    rng = np.random.default_rng(14 + planar)
    trials = 100
    same_count = accurate = matched = 0
    for _ in range(trials):
        xq, xr, R, t = make_scene(rng, planar=planar)
        ours = essentials(xq, xr)
        theirs = poselib.essential_matrix_5pt(unit(xq), unit(xr))
        same_count += len(ours) == len(theirs)
        for E in theirs:
            if essential_residual(E) < 1e-10:
                accurate += 1
                matched += min((e_distance(E, F) for F in ours), default=np.inf) < 1e-6
        poses = relpose(xq, xr)
        for q in poselib.relpose_5pt(unit(xq), unit(xr)):
            qt = q.t / np.linalg.norm(q.t)
            Eq = essential_from_relpose(q.R, qt)
            if np.abs(np.einsum("ni,ij,nj->n", unit(xr), Eq, unit(xq))).max() < 1e-11:
                accurate += 1
                matched += any(max(np.abs(p.R - q.R).max(), np.abs(p.t - qt).max()) < 1e-6 for p in poses)
        assert best_error(poses, R, t) < 1e-8
    assert same_count >= 0.95 * trials
    assert matched >= 0.99 * accurate


def test_nister_and_stewenius_agree():
    rng = np.random.default_rng(15)
    agree = 0
    for i in range(150):
        xq, xr, _, _ = make_scene(rng, planar=bool(i % 2))
        A = essentials_5p_nister(xq, xr)
        B = essentials_5p_stewenius(xq, xr)
        agree += sets_agree(A, B, 1e-8) and sets_agree(B, A, 1e-8)
    assert agree >= 147  # near-double real roots may be counted differently


# ---- building blocks ----------------------------------------------------------------------------


def test_cubic_constraints_match_direct_evaluation():
    rng = np.random.default_rng(16)
    for _ in range(10):
        basis = np.linalg.qr(rng.normal(size=(9, 4)))[0]
        C = five_point_constraints(basis)
        for _ in range(5):
            x, y, z = rng.normal(size=3)
            E = (basis @ np.array([x, y, z, 1.0])).reshape(3, 3)
            EEt = E @ E.T
            direct = np.concatenate([(2 * EEt @ E - np.trace(EEt) * E).ravel(), [np.linalg.det(E)]])
            monomials = np.array([x**a * y**b * z**c for a, b, c in MONOMIALS])
            assert np.allclose(C @ monomials, direct, rtol=1e-12, atol=1e-12)
