"""The single-call solver APIs: the compiled fast path and the checked slow path agree.

Plain C-contiguous float64 arrays go straight into one validating numba kernel; lists, other
dtypes, strided views, read-only arrays and (N, 2) points go through the full checks first.
Both must give the same poses, and invalid values the same one-line message.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from two_view_scenes import make_scene

import planarloc.solvers as S
from planarloc.geometry.epipolar import triangulation_depths
from planarloc.geometry.pose import Pose, rotation_error_deg
from planarloc.geometry.validation import InputError

RELPOSE = {  # name: (function, number of matches, planar scene)
    "relpose_planar_2p": (S.relpose_planar_2p, 2, True),
    "relpose_5p_nister": (S.relpose_5p_nister, 7, False),
    "relpose_5p_stewenius": (S.relpose_5p_stewenius, 7, False),
    "relpose_8p (8)": (S.relpose_8p, 8, False),
    "relpose_8p (12)": (S.relpose_8p, 12, False),
    "essentials_5p_nister": (S.essentials_5p_nister, 5, False),
    "essentials_5p_stewenius": (S.essentials_5p_stewenius, 5, False),
    "essential_8p": (S.essential_8p, 9, False),
}


def _arrays(result: list) -> list[np.ndarray]:
    return [
        np.concatenate([r.R.ravel(), r.t]) if isinstance(r, Pose) else np.asarray(r).ravel() for r in result
    ]


def _same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for x, y in zip(_arrays(a), _arrays(b)):
        np.testing.assert_array_equal(x, y)


def _variants(x: np.ndarray) -> dict[str, object]:
    """The same rays in every form the slow path accepts."""
    read_only = x.copy()
    read_only.setflags(write=False)
    strided = np.zeros((x.shape[0], 6))
    strided[:, ::2] = x
    return {
        "list": x.tolist(),
        "fortran": np.asfortranarray(x),
        "strided": strided[:, ::2],
        "read-only": read_only,
        "float32": x.astype(np.float32),
    }


@pytest.mark.parametrize("name", RELPOSE)
def test_fast_and_slow_path_give_identical_results(name: str) -> None:
    fn, n, planar = RELPOSE[name]
    rng = np.random.default_rng(3)
    for _ in range(5):
        xq, xr, _, _ = make_scene(rng, n=n, planar=planar)
        fast = fn(xq, xr)
        assert fast, "a noise-free scene has a solution"
        vqs, vrs = _variants(xq), _variants(xr)
        for kind in vqs:
            if kind == "float32":  # rounded values: compare to the same values in float64
                as64 = fn(vqs[kind].astype(np.float64), vrs[kind].astype(np.float64))
                _same(fn(vqs[kind], vrs[kind]), as64)
            else:
                _same(fn(vqs[kind], vrs[kind]), fast)


def test_planar_accepts_normalized_points_like_rays() -> None:
    rng = np.random.default_rng(4)
    xq, xr, _, _ = make_scene(rng, n=2, planar=True)
    _same(S.relpose_planar_2p(xq[:, :2].copy(), xr[:, :2].copy()), S.relpose_planar_2p(xq, xr))


@pytest.mark.parametrize("name", RELPOSE)
@pytest.mark.parametrize("bad", [np.nan, np.inf, "zero"])
def test_invalid_values_give_the_message_of_the_full_checks(name: str, bad) -> None:
    fn, n, planar = RELPOSE[name]
    xq, xr, _, _ = make_scene(np.random.default_rng(5), n=n, planar=planar)
    q = xq.copy()
    if bad == "zero":
        q[1] = 0.0
    else:
        q[1, 2] = bad
    messages = []
    for value in (q, q.tolist()):  # fast path (ndarray) and slow path (list)
        try:
            result = fn(value, xr)
        except InputError as exc:
            messages.append(str(exc))
        else:
            messages.append(result)
    if bad == "zero" and name == "relpose_planar_2p":
        assert messages == [[], []]  # planar: a zero ray gives no solution, as documented
    else:
        assert isinstance(messages[0], str) and messages[0] == messages[1]
        expected = "x_query[1] is a zero vector" if bad == "zero" else "NaN or inf (first at index (1, 2))"
        assert expected in messages[0]


@pytest.mark.parametrize("name", RELPOSE)
def test_wrong_shapes_raise_the_usual_message(name: str) -> None:
    fn, n, planar = RELPOSE[name]
    xq, xr, _, _ = make_scene(np.random.default_rng(6), n=n, planar=planar)
    with pytest.raises(InputError, match=r"x_query: expected shape"):
        fn(np.ones((n, 4)), xr)
    with pytest.raises(InputError, match="x_query|x_ref"):
        fn(xq, xr[:-1])


def test_returned_poses_are_immutable_and_independent_of_the_input() -> None:
    xq, xr, _, _ = make_scene(np.random.default_rng(7), n=6)
    poses = S.relpose_5p_nister(xq, xr)
    before = [(p.R.copy(), p.t.copy()) for p in poses]
    xq[:] = 1.0
    for p, (R, t) in zip(poses, before):
        assert not p.R.flags.writeable and not p.t.flags.writeable
        with pytest.raises(ValueError):
            p.R[0, 0] = 2.0
        np.testing.assert_array_equal(p.R, R)
        np.testing.assert_array_equal(p.t, t)
        assert abs(np.linalg.det(p.R) - 1.0) < 1e-9 and abs(np.linalg.norm(p.t) - 1.0) < 1e-9


def test_abspose_up2p_paths_agree() -> None:
    rng = np.random.default_rng(8)
    R = Rotation.from_rotvec([0.0, 0.4, 0.0]).as_matrix()
    X = rng.uniform(-3, 3, (2, 3)) + [0.0, 0.0, 8.0]
    Xc = X @ R.T + [0.5, 0.0, 1.0]
    x = Xc / Xc[:, 2:]
    fast = S.abspose_up2p(x, X)
    assert fast
    _same(S.abspose_up2p(x.tolist(), X.tolist()), fast)
    _same(S.abspose_up2p(np.asfortranarray(x), X), fast)
    bad = x.copy()
    bad[0, 1] = np.nan
    with pytest.raises(InputError, match=r"x_query: contains NaN or inf \(first at index \(0, 1\)\)"):
        S.abspose_up2p(bad, X)


# ---- absolute poses from relative ones: the compiled kernels against Pose algebra ----------------


def _random_pose(rng: np.random.Generator) -> Pose:
    return Pose.from_center(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-5, 5, 3))


def test_abspose_2p2p_matches_pose_algebra() -> None:
    rng = np.random.default_rng(9)
    for _ in range(20):
        query, ref, ref2 = _random_pose(rng), _random_pose(rng), _random_pose(rng)
        rel, rel2 = ref @ query.inverse(), ref2 @ query.inverse()
        rel = Pose(rel.R, rel.t / np.linalg.norm(rel.t))
        rel2 = Pose(rel2.R, rel2.t / np.linalg.norm(rel2.t))
        res = S.abspose_2p2p(rel, rel2, ref.inverse().inverse(), ref2)  # inverse(): transposed arrays
        j_from_j2 = ref @ ref2.inverse()
        t2_in_1 = rel.R @ rel2.R.T @ rel2.t
        rcheck = rotation_error_deg(j_from_j2.R, rel.R @ rel2.R.T)
        assert res.rcheck_deg == pytest.approx(rcheck, abs=1e-5)  # ~0: arccos near 1 amplifies rounding
        assert res.sin_parallax == pytest.approx(np.linalg.norm(np.cross(rel.t, t2_in_1)), abs=1e-12)
        np.testing.assert_allclose(res.pose.R, query.R, atol=1e-9)
        np.testing.assert_allclose(res.pose.center, query.center, atol=1e-7)
        assert not res.regularised and res.rho > 0 and res.rho2 > 0
    with pytest.raises(ValueError, match="non-zero"):
        S.abspose_2p2p(Pose(np.eye(3), np.zeros(3)), rel2, ref, ref2)


def test_abspose_2p1p_matches_pose_algebra_and_its_checks() -> None:
    rng = np.random.default_rng(10)
    done = 0
    while done < 20:
        query, ref, ref2 = _random_pose(rng), _random_pose(rng), _random_pose(rng)
        X = rng.uniform(-10, 10, 3)
        Yq, Y2 = query.transform(X[None])[0], ref2.transform(X[None])[0]
        if Yq[2] < 0.5 or Y2[2] < 0.5:
            continue
        rel = ref @ query.inverse()
        rel = Pose(rel.R, rel.t / np.linalg.norm(rel.t))
        xq, x2 = Yq / Yq[2], Y2 / Y2[2]
        (res,) = S.abspose_2p1p(rel, ref, ref2, xq, x2)
        np.testing.assert_allclose(res.pose.R, query.R, atol=1e-9)
        np.testing.assert_allclose(res.pose.center, query.center, atol=1e-7)
        j2_from_q = ref2 @ res.pose.inverse()
        depths = triangulation_depths(j2_from_q.R, j2_from_q.t, xq[None], x2[None])[0]
        np.testing.assert_allclose(res.depths, depths, rtol=1e-9)
        (slow,) = S.abspose_2p1p(rel, ref, ref2, xq.tolist(), list(x2))
        np.testing.assert_array_equal(slow.pose.R, res.pose.R)
        assert slow.rho == res.rho
        done += 1
    with pytest.raises(InputError, match=r"x_ref2: contains NaN"):
        S.abspose_2p1p(rel, ref, ref2, xq, np.array([np.nan, 0.0, 1.0]))
    with pytest.raises(InputError, match=r"x_query: expected shape \(3,\)"):
        S.abspose_2p1p(rel, ref, ref2, xq[:2].copy(), x2)
    assert S.abspose_2p1p(Pose(rel.R, np.zeros(3)), ref, ref2, xq, x2) == []
