"""The consensus 2p1p kernels (robust/consensus_scale.py) on constructed inputs.

Stage 1 (:func:`planar_relative_candidates`) must rank the true relative pose first among
samples of one pair; stage 2 (:func:`hypotheses_2p1p_consensus`) must recover the scale that
most matches of the other pairs agree on, ignore outliers, and reject a scale that places
the voters behind the cameras (Pdcheck).
"""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.robust.consensus_scale import (
    ConsensusSettings,
    RelativeCandidates,
    hypotheses_2p1p_consensus,
    planar_relative_candidates,
)
from planarloc.robust.hypotheses import DEGENERATE, HYPOTHESES, PDCHECK, Hypotheses
from planarloc.robust.problem import ProblemArrays

F = np.array([800.0, 800.0])


def planar_pose(yaw: float, cx: float, cz: float) -> Pose:
    return Pose.from_center(rotation_from_yaw(yaw), [cx, 0.0, cz])


Q = planar_pose(0.3, 1.0, -2.0)
REFS = [planar_pose(-0.4, -2.0, 1.0), planar_pose(1.0, 3.0, 2.0), planar_pose(0.2, 0.5, 3.5)]


def matches(
    rng: np.random.Generator, ref: Pose, n: int, outliers: int = 0, query: Pose = Q
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` matches of points in front of ``query`` and ``ref`` (rays (x, y, 1)); the last
    ``outliers`` have a random reference ray."""
    xq, xr = [], []
    while len(xq) < n:
        X = rng.uniform(-10.0, 10.0, 3)
        a, b = query.R @ X + query.t, ref.R @ X + ref.t
        if (
            a[2] > 1.0
            and b[2] > 1.0
            and abs(a[0]) < a[2]
            and abs(b[0]) < b[2]
            and abs(a[1]) < a[2]
            and abs(b[1]) < b[2]
        ):
            xq.append(a / a[2])
            xr.append(b / b[2])
    xq, xr = np.array(xq), np.array(xr)
    if outliers:
        xr[n - outliers :, :2] = rng.uniform(-0.8, 0.8, (outliers, 2))
    return xq, xr


def problem(rng: np.random.Generator, n: int, outliers: int = 0, third_query: Pose = Q) -> ProblemArrays:
    """Pair 0 seen from Q; pairs 1 and 2 seen from ``third_query``."""
    parts = [matches(rng, r, n, outliers, Q if p == 0 else third_query) for p, r in enumerate(REFS)]
    return ProblemArrays(
        xq=np.ascontiguousarray(np.vstack([q for q, _ in parts])),
        xr=np.ascontiguousarray(np.vstack([r for _, r in parts])),
        pair=np.repeat(np.arange(3, dtype=np.int64), n),
        offsets=np.arange(0, 3 * n + 1, n, dtype=np.int64),
        f_query=np.concatenate([F, F]),
        f_ref=np.tile(F, (3, 1)),
        ref_R=np.ascontiguousarray(np.stack([r.R for r in REFS])),
        ref_t=np.ascontiguousarray(np.stack([r.t for r in REFS])),
        xq3d=np.zeros((0, 3)),
        X3d=np.zeros((0, 3)),
    )


def true_relative(p: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rel = REFS[p] @ Q.inverse()
    return rel.R.copy(), rel.t / np.linalg.norm(rel.t)


def consensus(
    pb: ProblemArrays,
    R: np.ndarray,
    t: np.ndarray,
    peaks: int = 1,
    max_votes: int = 1000,
    threshold_px: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out_R, out_t = np.empty((peaks, 3, 3)), np.empty((peaks, 3))
    counters = np.zeros(5, dtype=np.int64)
    m = hypotheses_2p1p_consensus(
        RelativeCandidates(R[None], t[None], np.array([0]), counters),
        pb,
        ConsensusSettings(threshold_px**2, top_k=1, max_scored=max_votes, peaks=peaks, max_votes=max_votes),
        Hypotheses(out_R, out_t, counters),
    )
    return out_R[:m], out_t[:m], counters


def centre_error(R: np.ndarray, t: np.ndarray) -> float:
    return float(np.linalg.norm(-R.T @ t - Q.center))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_consensus_recovers_true_scale_without_noise(seed: int) -> None:
    pb = problem(np.random.default_rng(seed), 30)
    R, t, counters = consensus(pb, *true_relative())
    assert len(R) == 1 and counters[HYPOTHESES] == 1
    np.testing.assert_allclose(R[0], Q.R, atol=1e-9)
    # Every interval contains the true ρ; the maximum is the intersection, a few mm wide.
    assert centre_error(R[0], t[0]) < 0.02


@pytest.mark.parametrize("seed", [0, 1])
def test_consensus_ignores_outliers_and_strided_votes_agree(seed: int) -> None:
    pb = problem(np.random.default_rng(seed), 60, outliers=36)  # 60 % outliers in every pair
    R, t, _ = consensus(pb, *true_relative())
    assert centre_error(R[0], t[0]) < 0.05
    R2, t2, _ = consensus(pb, *true_relative(), max_votes=40)  # every third match votes
    assert centre_error(R2[0], t2[0]) < 0.1


def test_consensus_rejects_scale_behind_cameras() -> None:
    # The other pairs are seen from Q reflected through reference 0's centre: eq. (18) then
    # gives ρ < 0 for every match, which Pdcheck must reject (no hypothesis returned).
    reflected = Pose.from_center(Q.R, 2.0 * REFS[0].center - Q.center)
    pb = problem(np.random.default_rng(3), 30, third_query=reflected)
    R, _, counters = consensus(pb, *true_relative())
    assert not any(np.abs(Ri - Q.R).max() < 1e-6 and centre_error(Ri, ti) < 0.5 for Ri, ti in zip(R, _))
    assert counters[PDCHECK] + counters[DEGENERATE] >= 1


def test_consensus_second_peak_is_separated() -> None:
    pb = problem(np.random.default_rng(4), 40, outliers=20)
    R, t, counters = consensus(pb, *true_relative(), peaks=2)
    assert 1 <= len(R) <= 2 and counters[HYPOTHESES] == len(R) + counters[PDCHECK]
    if len(R) == 2:
        ca, cb = -R[0].T @ t[0], -R[1].T @ t[1]
        rho_a = np.linalg.norm(ca - REFS[0].center)
        rho_b = np.linalg.norm(cb - REFS[0].center)
        assert abs(rho_a - rho_b) > 0.1 * rho_a


@pytest.mark.parametrize("outliers", [0, 12])
def test_stage1_ranks_true_relative_pose_first(outliers: int) -> None:
    rng = np.random.default_rng(5)
    pb = problem(rng, 30, outliers=outliers)
    # samples: inlier pairs of matches of pair 0, plus samples with an outlier
    S = 40
    samples = np.stack([rng.choice(30, 2, replace=False) for _ in range(S)]).astype(np.int64)
    out = RelativeCandidates.empty(6, np.zeros(5, dtype=np.int64))
    out_R, out_t, out_pair = out.R, out.t, out.pair
    c = planar_relative_candidates(
        samples, pb, ConsensusSettings(4.0, top_k=2, max_scored=1000, peaks=1, max_votes=2000), out
    )
    assert 1 <= c <= 2 and (out_pair[:c] == 0).all()
    R_true, t_true = true_relative()
    np.testing.assert_allclose(out_R[0], R_true, atol=1e-8)
    np.testing.assert_allclose(out_t[0], t_true, atol=1e-8)
    if c == 2:  # the runner-up is a different model, not the same pose found twice
        assert np.abs(out_R[1] - out_R[0]).max() > 1e-6 or np.abs(out_t[1] - out_t[0]).max() > 1e-6
