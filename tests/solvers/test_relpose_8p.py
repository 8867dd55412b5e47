"""Tests of the normalized 8-point solver, with OpenCV and PoseLib as oracles."""

from __future__ import annotations

import cv2
import numpy as np
import poselib
import pytest
from two_view_scenes import e_distance, pose_error, random_relpose, unit
from two_view_scenes import make_scene as _make_scene

from planarloc.geometry.epipolar import essential_from_relpose
from planarloc.geometry.validation import InputError
from planarloc.solvers.relpose_8p import essential_8p, relpose_8p, relpose_8p_batch


def make_scene(rng, n=8, **kw):
    return _make_scene(rng, n, **kw)


# ---- recovery -----------------------------------------------------------------------------------


@pytest.mark.parametrize("planar", [False, True], ids=["6dof", "planar"])
@pytest.mark.parametrize("n", [8, 30])
@pytest.mark.parametrize("seed", range(3))
def test_exact_recovery(planar, n, seed):
    rng = np.random.default_rng(10 * seed + n + planar)
    for _ in range(40):
        xq, xr, R, t = make_scene(rng, n=n, planar=planar)
        Es = essential_8p(xq, xr)
        assert len(Es) == 1
        E = Es[0]
        assert np.linalg.norm(E) == pytest.approx(1.0)
        assert np.allclose(np.linalg.svd(E, compute_uv=False), [2**-0.5, 2**-0.5, 0.0], atol=1e-12)
        assert e_distance(E, essential_from_relpose(R, t)) < 1e-8
        poses = relpose_8p(xq, xr)
        assert len(poses) == 1
        assert pose_error(poses[0], R, t) < 1e-8


def test_wide_angle_bearings():
    """Rays far from the optical axis (|z| small or negative) use unit-bearing normalization."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        R, t = random_relpose(rng, max_angle=np.pi)
        X = rng.uniform(-10, 10, size=(40, 3))
        Y = X @ R.T + t
        keep = (np.linalg.norm(X, axis=1) > 0.5) & (np.linalg.norm(Y, axis=1) > 0.5)
        xq = unit(X[keep]) * rng.uniform(0.1, 10, size=(keep.sum(), 1))
        xr = unit(Y[keep]) * rng.uniform(0.1, 10, size=(keep.sum(), 1))
        poses = relpose_8p(xq, xr)
        assert len(poses) == 1 and pose_error(poses[0], R, t / np.linalg.norm(t)) < 1e-8


def test_small_noise_near_exact():
    rng = np.random.default_rng(5)
    errors = []
    for _ in range(50):
        xq, xr, R, t = make_scene(rng, n=50, noise=1e-7)
        poses = relpose_8p(xq, xr)
        assert len(poses) == 1
        errors.append(pose_error(poses[0], R, t))
    assert max(errors) < 1e-4 and np.median(errors) < 1e-5


# ---- oracles ------------------------------------------------------------------------------------


@pytest.mark.parametrize("planar", [False, True], ids=["6dof", "planar"])
def test_agrees_with_opencv(planar):
    rng = np.random.default_rng(6 + planar)
    for _ in range(15):
        xq, xr, R, t = make_scene(rng, n=20, planar=planar)
        E_cv, _ = cv2.findEssentialMat(xq[:, :2], xr[:, :2], np.eye(3), method=cv2.LMEDS)
        E_cv = E_cv[:3]  # OpenCV may stack several candidates; exact data: the first is exact
        (E,) = essential_8p(xq, xr)
        assert e_distance(E, E_cv) < 1e-6
        _, R_cv, t_cv, _ = cv2.recoverPose(E_cv, xq[:, :2], xr[:, :2], np.eye(3))
        (pose,) = relpose_8p(xq, xr)
        assert np.abs(pose.R - R_cv).max() < 1e-6
        assert np.abs(pose.t - t_cv.ravel()).max() < 1e-6
    # with noise both land near the truth and near each other
    errs = []
    for _ in range(15):
        xq, xr, R, t = make_scene(rng, n=100, planar=planar, noise=1e-4)
        E_cv, _ = cv2.findEssentialMat(xq[:, :2], xr[:, :2], np.eye(3), method=cv2.LMEDS)
        _, R_cv, _, _ = cv2.recoverPose(E_cv[:3], xq[:, :2], xr[:, :2], np.eye(3))
        (pose,) = relpose_8p(xq, xr)
        errs.append(np.abs(pose.R - R_cv).max())
    assert np.median(errs) < 1e-2


def test_agrees_with_poselib():
    rng = np.random.default_rng(8)
    for i in range(30):
        xq, xr, R, t = make_scene(rng, n=8 + i, planar=bool(i % 2))
        (theirs,) = poselib.relpose_8pt(unit(xq), unit(xr))
        (ours,) = relpose_8p(xq, xr)
        assert np.abs(ours.R - theirs.R).max() < 1e-8
        assert np.abs(ours.t - theirs.t / np.linalg.norm(theirs.t)).max() < 1e-8


# ---- degenerate and invalid input ---------------------------------------------------------------


def degenerate_samples():
    rng = np.random.default_rng(9)
    R, t = random_relpose(rng)
    xq, xr, _, _ = make_scene(rng, n=12, R=R, t=t)
    out = {}
    idx = [0, 1, 2, 3, 4, 5, 6, 0, 1, 2]  # repeated correspondences: only 7 distinct
    out["7 distinct points"] = (xq[idx], xr[idx])
    out["all points identical"] = (np.repeat(xq[:1], 9, axis=0), np.repeat(xr[:1], 9, axis=0))
    Y = xq @ R.T
    out["pure rotation"] = (xq, Y / Y[:, 2:])
    # all points on one plane (critical for the linear 8-point method)
    n = np.array([0.2, -0.3, 1.0])
    P = rng.uniform(-5, 5, size=(12, 3))
    P[:, 2] = (8.0 - P[:, :2] @ n[:2]) / n[2]
    Q = P @ R.T + t
    out["coplanar points"] = (P / P[:, 2:], Q / Q[:, 2:])
    d = R @ xq[0]
    xr_inf = xr.copy()
    xr_inf[0] = d / d[2]
    out["one point at infinity"] = (xq, xr_inf)
    xq_behind = xq.copy()
    xq_behind[4] *= -1.0  # same epipolar constraint, but the ray points backwards
    out["one point behind the camera"] = (xq_behind, xr)
    return out


DEGENERATE = degenerate_samples()


@pytest.mark.parametrize("case", DEGENERATE)
def test_degenerate_input_gives_no_pose(case):
    xq, xr = DEGENERATE[case]
    assert relpose_8p(xq, xr) == []
    if case not in ("one point at infinity", "one point behind the camera"):
        assert essential_8p(xq, xr) == []
    R, t, valid = relpose_8p_batch(xq[None, :8], xr[None, :8])  # the first 8 are degenerate too
    assert not valid.any() and np.isnan(R).all() and np.isnan(t).all()


def test_invalid_input_raises():
    rng = np.random.default_rng(10)
    xq, xr, _, _ = make_scene(rng, n=9)
    with pytest.raises(InputError, match="at least 8 rows"):
        relpose_8p(xq[:7], xr[:7])
    with pytest.raises(InputError, match="at least 8 rows"):
        essential_8p(xq[:7], xr[:7])
    with pytest.raises(InputError, match="same number of rows"):
        relpose_8p(xq, xr[:8])
    with pytest.raises(InputError, match=r"expected shape \(N, 3\)"):
        relpose_8p(xq[:, :2], xr[:, :2])
    bad = xq.copy()
    bad[0, 1] = np.nan
    with pytest.raises(InputError, match="NaN or inf"):
        relpose_8p(bad, xr)
    bad = xr.copy()
    bad[2] = 0.0
    with pytest.raises(InputError, match=r"x_ref\[2\] is a zero vector"):
        relpose_8p(xq, bad)
    with pytest.raises(InputError, match=r"expected shape \(N, 8, 3\)"):
        relpose_8p_batch(xq[None], xr[None])
    with pytest.raises(ValueError):
        relpose_8p_batch(np.full((2, 8, 3), np.inf), np.ones((2, 8, 3)))


# ---- batched API --------------------------------------------------------------------------------


def test_batch_matches_single_calls():
    rng = np.random.default_rng(11)
    scenes = [make_scene(rng, n=8, planar=bool(i % 2)) for i in range(50)]
    XQ = np.stack([s[0] for s in scenes])
    XR = np.stack([s[1] for s in scenes])
    XQ[3], XR[3] = DEGENERATE["pure rotation"][0][:8], DEGENERATE["pure rotation"][1][:8]
    XQ[9], XR[9] = DEGENERATE["coplanar points"][0][:8], DEGENERATE["coplanar points"][1][:8]
    R, t, valid = relpose_8p_batch(XQ, XR)
    assert R.shape == (50, 1, 3, 3) and t.shape == (50, 1, 3) and valid.shape == (50, 1)
    assert not valid[3, 0] and not valid[9, 0]
    for m in range(50):
        single = relpose_8p(XQ[m], XR[m])
        assert len(single) == int(valid[m, 0])
        if single:
            assert np.abs(R[m, 0] - single[0].R).max() < 1e-9
            assert np.abs(t[m, 0] - single[0].t).max() < 1e-9
            assert pose_error(single[0], scenes[m][2], scenes[m][3]) < 1e-8
        else:
            assert np.isnan(R[m]).all() and np.isnan(t[m]).all()
