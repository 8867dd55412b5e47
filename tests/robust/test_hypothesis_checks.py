"""The multiple checking of paper Sec. IV-B on constructed inputs: each check rejects a
hypothesis that must fail it, counts it, and does not return it; the unperturbed input passes.

The numba kernels are called directly so that each check is isolated from sampling and scoring.
"""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.hypotheses import (
    CONSISTENCY,
    DEGENERATE,
    HYPOTHESES,
    PDCHECK,
    RCHECK,
    Hypotheses,
    RelativePoses,
    hypotheses_2p1p,
    hypotheses_from_relative_poses,
)
from planarloc.robust.options import RansacOptions
from planarloc.robust.problem import ProblemArrays

COS_2DEG = float(np.cos(np.radians(2.0)))
E_Y = np.array([0.0, 1.0, 0.0])


def planar_pose(yaw: float, cx: float, cz: float) -> Pose:
    """Upright ``cam_from_world`` with centre (cx, 0, cz)."""
    return Pose.from_center(rotation_from_yaw(yaw), [cx, 0.0, cz])


# Query Q and references J, K in general position (not collinear).
Q = planar_pose(0.3, 1.0, -2.0)
J = planar_pose(-0.4, -2.0, 1.0)
K = planar_pose(1.0, 3.0, 2.0)
# The query reflected through J's centre: same rotation, j_from_query translation = -ρ t̃.
Q_REFLECTED = Pose.from_center(Q.R, 2.0 * J.center - Q.center)


def unit_relative(ref: Pose, query: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``ref_from_query`` rotation and unit translation."""
    rel = ref @ query.inverse()
    return rel.R.copy(), rel.t / np.linalg.norm(rel.t)


def covisible_point(cams: tuple[Pose, ...], seed: int) -> np.ndarray:
    """A world point in front of every camera (depth > 1), inside a 90° field of view."""
    rng = np.random.default_rng(seed)
    for _ in range(100_000):
        X = rng.uniform(-12.0, 12.0, 3)
        Xc = [c.R @ X + c.t for c in cams]
        if all(x[2] > 1.0 and abs(x[0]) < x[2] and abs(x[1]) < x[2] for x in Xc):
            return X
    raise RuntimeError("no co-visible point found")


def ray(cam: Pose, X: np.ndarray) -> np.ndarray:
    Xc = cam.R @ X + cam.t
    assert Xc[2] > 0
    return Xc / Xc[2]


def yaw_rotation_deg(deg: float) -> np.ndarray:
    return rotation_from_yaw(np.radians(deg))


def problem_arrays(
    xq: np.ndarray, xr: np.ndarray, refs: tuple[Pose, ...], xq3d: np.ndarray, X3d: np.ndarray
) -> ProblemArrays:
    """The kernels' record of matches ``xq``, ``xr`` (all of pair 0) to the references ``refs``
    (unit focal lengths) with the 2D-3D constraints ``xq3d``, ``X3d``."""
    n, P = len(xq), len(refs)
    return ProblemArrays(
        np.ascontiguousarray(xq, dtype=float),
        np.ascontiguousarray(xr, dtype=float),
        np.zeros(n, dtype=np.int64),
        np.array([0] + [n] * P, dtype=np.int64),
        np.ones(4),
        np.ones((P, 2)),
        np.ascontiguousarray(np.stack([r.R for r in refs])),
        np.ascontiguousarray(np.stack([r.t for r in refs])),
        np.ascontiguousarray(xq3d, dtype=float),
        np.ascontiguousarray(X3d, dtype=float),
    )


def same_pose(R: np.ndarray, t: np.ndarray, truth: Pose, tol: float = 1e-8) -> bool:
    return bool(np.abs(R - truth.R).max() < tol and np.linalg.norm(-R.T @ t - truth.center) < tol)


# --------------------------------------------------------------------------------------------
# 2p2p and baselines: hypotheses_from_relative_poses
# --------------------------------------------------------------------------------------------
def run_relative(
    cands_a: list[tuple[np.ndarray, np.ndarray]],
    cands_b: list[tuple[np.ndarray, np.ndarray]],
    j: Pose = J,
    k: Pose = K,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the kernel on one sample with the given candidate relative poses to j and k."""
    A = max(len(cands_a), len(cands_b))
    Ra = np.zeros((1, A, 3, 3))
    ta = np.zeros((1, A, 3))
    va = np.zeros((1, A), dtype=np.bool_)
    Rb, tb, vb = Ra.copy(), ta.copy(), va.copy()
    for cands, (Rx, tx, vx) in ((cands_a, (Ra, ta, va)), (cands_b, (Rb, tb, vb))):
        for i, (R, t) in enumerate(cands):
            Rx[0, i], tx[0, i], vx[0, i] = R, t, True
    out_R = np.empty((A * A, 3, 3))
    out_t = np.empty((A * A, 3))
    counters = np.zeros(5, dtype=np.int64)
    n = hypotheses_from_relative_poses(
        RelativePoses(Ra, ta, va),
        RelativePoses(Rb, tb, vb),
        np.array([0]),
        np.array([1]),
        np.ascontiguousarray(np.stack([j.R, k.R])),
        np.ascontiguousarray(np.stack([j.t, k.t])),
        COS_2DEG,
        COS_2DEG,
        Hypotheses(out_R, out_t, counters),
    )
    return out_R[:n], out_t[:n], counters


def test_relative_true_poses_pass_every_check() -> None:
    R, t, counters = run_relative([unit_relative(J, Q)], [unit_relative(K, Q)])
    assert len(R) == 1 and same_pose(R[0], t[0], Q)
    assert counters.tolist() == [1, 0, 0, 0, 0]


@pytest.mark.parametrize("error_deg", [3.0, 10.0, 90.0])
def test_rcheck_rejects_inconsistent_rotations(error_deg: float) -> None:
    Rb, tb = unit_relative(K, Q)
    # R_a R_bᵀ now differs from the map's R_j R_kᵀ by error_deg > e_th = 2°.
    R, _, counters = run_relative([unit_relative(J, Q)], [(yaw_rotation_deg(error_deg) @ Rb, tb)])
    assert len(R) == 0
    assert counters[HYPOTHESES] == 1 and counters[RCHECK] == 1
    assert counters[PDCHECK] == counters[CONSISTENCY] == counters[DEGENERATE] == 0


def test_rcheck_is_relaxed_below_threshold() -> None:
    Rb, tb = unit_relative(K, Q)
    R, _, counters = run_relative([unit_relative(J, Q)], [(yaw_rotation_deg(1.0) @ Rb, tb)])
    assert counters[RCHECK] == 0 and len(R) == 1


def test_rcheck_rejected_candidate_is_not_returned_next_to_a_good_one() -> None:
    Ra, ta = unit_relative(J, Q)
    Rb, tb = unit_relative(K, Q)
    R, t, counters = run_relative([(Ra, ta)], [(yaw_rotation_deg(-5.0) @ Rb, tb), (Rb, tb)])
    assert counters[HYPOTHESES] == 2 and counters[RCHECK] == 1
    assert len(R) == 1 and same_pose(R[0], t[0], Q)


def test_pdcheck_rejects_negative_scales_after_triangulation() -> None:
    Ra, ta = unit_relative(J, Q)
    Rb, tb = unit_relative(K, Q)
    # Flipped directions intersect behind both references: ρ < 0 and ρ₂ < 0.
    R, _, counters = run_relative([(Ra, -ta)], [(Rb, -tb)])
    assert len(R) == 0
    assert counters[RCHECK] == 0 and counters[PDCHECK] == 1 and counters[CONSISTENCY] == 0


@pytest.mark.parametrize("tilt_deg", [5.0, 10.0, 30.0])
def test_consistency_rejects_direction_mismatch(tilt_deg: float) -> None:
    Ra, ta = unit_relative(J, Q)
    Rb, tb = unit_relative(K, Q)
    # t̃₂ tilted out of the plane: the rays no longer meet and the triangulated centre,
    # seen from K, is tilt_deg away from t̃₂ (> α_th = 2°). Rcheck and Pdcheck still pass.
    a = np.radians(tilt_deg)
    tb_tilted = np.cos(a) * tb + np.sin(a) * E_Y
    R, _, counters = run_relative([(Ra, ta)], [(Rb, tb_tilted)])
    assert len(R) == 0
    assert counters[RCHECK] == 0 and counters[PDCHECK] == 0 and counters[CONSISTENCY] == 1


def test_consistency_passes_small_mismatch() -> None:
    Ra, ta = unit_relative(J, Q)
    Rb, tb = unit_relative(K, Q)
    a = np.radians(1.0)
    R, _, counters = run_relative([(Ra, ta)], [(Rb, np.cos(a) * tb + np.sin(a) * E_Y)])
    assert counters[CONSISTENCY] == 0 and len(R) == 1


def test_collinear_centres_are_degenerate_not_a_position() -> None:
    # Query between two references on one line: the rays from j and k coincide (eq. 15).
    j, k, q = planar_pose(0.1, 0.0, 4.0), planar_pose(-0.2, 0.0, -3.0), planar_pose(0.05, 0.0, 0.5)
    R, _, counters = run_relative([unit_relative(j, q)], [unit_relative(k, q)], j=j, k=k)
    assert len(R) == 0
    assert counters[DEGENERATE] == 1


# --------------------------------------------------------------------------------------------
# 2p1p: hypotheses_2p1p
# --------------------------------------------------------------------------------------------
def run_2p1p(
    third_query_cam: Pose, third_is_3d: bool, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two true Q-J matches plus a third datum observed from ``third_query_cam``.

    The third datum is a Q-K match (or a 2D-3D constraint) of a point seen from
    ``third_query_cam`` instead of Q. With Q itself it is consistent; with Q reflected
    through J's centre it is satisfied exactly by ρ = -|c_Q - c_J| (eq. 18 is linear in ρ).
    """
    X1, X2 = covisible_point((Q, J), seed), covisible_point((Q, J), seed + 1)
    X3 = covisible_point((third_query_cam, K), seed + 2)
    xq = np.ascontiguousarray([ray(Q, X1), ray(Q, X2), ray(third_query_cam, X3)])
    xr = np.ascontiguousarray([ray(J, X1), ray(J, X2), ray(K, X3)])
    if third_is_3d:
        xq3d, X3d, third = np.ascontiguousarray([ray(third_query_cam, X3)]), np.ascontiguousarray([X3]), 0
    else:
        xq3d, X3d, third = np.zeros((0, 3)), np.zeros((0, 3)), 2
    out_R = np.empty((2, 3, 3))
    out_t = np.empty((2, 3))
    counters = np.zeros(5, dtype=np.int64)
    n = hypotheses_2p1p(
        np.array([[0, 1, third]]),
        np.array([third_is_3d]),
        np.array([0]),
        np.array([1]),
        problem_arrays(xq, xr, (J, K), xq3d, X3d),
        Hypotheses(out_R, out_t, counters),
    )
    return out_R[:n], out_t[:n], counters


@pytest.mark.parametrize("third_is_3d", [False, True])
@pytest.mark.parametrize("seed", [0, 10, 20])
def test_2p1p_true_sample_gives_true_pose(third_is_3d: bool, seed: int) -> None:
    R, t, counters = run_2p1p(Q, third_is_3d, seed)
    assert any(same_pose(Ri, ti, Q) for Ri, ti in zip(R, t))
    assert counters[PDCHECK] <= counters[HYPOTHESES] - 1


@pytest.mark.parametrize("third_is_3d", [False, True])
@pytest.mark.parametrize("seed", [0, 10, 20])
def test_pdcheck_rejects_negative_scale_2p1p(third_is_3d: bool, seed: int) -> None:
    R, t, counters = run_2p1p(Q_REFLECTED, third_is_3d, seed)
    assert counters[PDCHECK] >= 1
    # Without Pdcheck the output would contain (R_Q, centre of Q_REFLECTED): the only
    # hypothesis with the true rotation. It must not be returned.
    assert not any(np.abs(Ri - Q.R).max() < 1e-6 for Ri in R)
    assert len(R) == counters[HYPOTHESES] - counters[PDCHECK] - counters[DEGENERATE]


# --------------------------------------------------------------------------------------------
# Statistics bookkeeping through the public API
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["2p1p", "2p2p"])
def test_statistics_account_for_every_hypothesis(scene, method: str) -> None:
    sc = scene(3, num_refs=5, matches_per_pair=50, noise_px=1.0, outlier_ratio=0.5)
    est = estimate_absolute_pose(
        sc.query_camera,
        sc.pairs,
        method,
        RansacOptions(max_iterations=100, min_iterations=100, structure="none", seed=3),
    )
    s = est.stats
    rejected = s.rejected_rcheck + s.rejected_pdcheck + s.rejected_consistency
    # A degenerate count is either a solver without solution (no hypothesis) or a hypothesis
    # whose scale is undetermined; every other hypothesis is rejected by one check or scored.
    assert s.hypotheses - rejected - s.rejected_degenerate <= s.scored <= s.hypotheses - rejected
    assert s.iterations == 100
    if method == "2p1p":
        # Consensus scale: at most ``peaks`` hypotheses per kept relative pose of each pair
        # (Pdcheck on the consensus scale is tested on the kernel below).
        assert s.hypotheses <= 2 * 3 * 5
    else:
        assert s.rejected_rcheck > 0
