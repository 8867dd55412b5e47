"""The search stages and refinement landings that run as single compiled calls
(:mod:`planarloc.robust.relative_stages`, :func:`~planarloc.robust.consensus_scale.consensus_2p1p`,
:func:`~planarloc.robust.final_refinement.restart_landings` and ``start_landings``), tested on
their own: noise-free scenes give back the true pose. Generated data only."""

from __future__ import annotations

import numpy as np

from planarloc.robust.consensus_scale import ConsensusSettings, consensus_2p1p
from planarloc.robust.estimators import Planar2p1pEstimator
from planarloc.robust.final_refinement import FinalRefiner, restart_landings, start_landings
from planarloc.robust.hypotheses import RelativePoses
from planarloc.robust.options import RansacOptions
from planarloc.robust.problem import build_problem
from planarloc.robust.relative_stages import hypotheses_of_relative_samples, relative_samples
from planarloc.solvers.relpose_5p_nister import relpose_5p_nister_batch_unchecked


def _closest(R: np.ndarray, t: np.ndarray, pose) -> tuple[float, float]:
    """Centre distance (m) and rotation difference (Frobenius) of the hypothesis nearest the pose."""
    centres = -np.einsum("nji,nj->ni", R, t)
    k = int(np.argmin(np.linalg.norm(centres - pose.center, axis=1)))
    return float(np.linalg.norm(centres[k] - pose.center)), float(np.linalg.norm(R[k] - pose.R))


def test_relative_samples_draw_distinct_matches_of_each_eligible_image(scene) -> None:
    sc = scene(11, num_refs=3, matches_per_pair=30, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    eligible = np.array([0, 2], dtype=np.int64)
    n, m = 7, 5
    pair, xq, xr = relative_samples(np.random.default_rng(0).random((2 * n, m)), pb.arrays, eligible, n, m)
    assert pair.tolist() == [0] * n + [2] * n
    for s in range(2 * n):
        lo, hi = pb.offsets[pair[s]], pb.offsets[pair[s] + 1]
        rows = [lo + int(np.flatnonzero((pb.xq[lo:hi] == xq[s, a]).all(axis=1))[0]) for a in range(m)]
        assert len(set(rows)) == m  # distinct matches, all of the sample's own image
        np.testing.assert_array_equal(pb.xr[rows], xr[s])


def test_relative_stages_recover_the_true_pose_from_noise_free_matches(scene) -> None:
    sc = scene(12, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    eligible = np.arange(3, dtype=np.int64)
    n = 4
    pair, xq, xr = relative_samples(np.random.default_rng(1).random((3 * n, 5)), pb.arrays, eligible, n, 5)
    R, t, valid = relpose_5p_nister_batch_unchecked(xq, xr)
    counters = np.zeros(5, dtype=np.int64)
    j, k = np.triu_indices(3, 1)
    Rh, th = hypotheses_of_relative_samples(
        RelativePoses(R, t, valid),
        pair,
        eligible,
        n,
        pb.arrays,
        4.0,
        3,
        j,
        k,
        np.cos(np.radians(2.0)),
        np.cos(np.radians(2.0)),
        counters,
    )
    assert len(Rh) >= 1 and counters[0] >= len(Rh)
    dc, dR = _closest(Rh, th, sc.query_pose)
    assert dc < 1e-8 and dR < 1e-8


def test_consensus_2p1p_recovers_the_true_pose_from_noise_free_matches(scene) -> None:
    sc = scene(13, num_refs=3, matches_per_pair=40, noise_px=0.0, outlier_ratio=0.3)
    pb = build_problem(sc.query_camera, sc.pairs)
    counters = np.zeros(5, dtype=np.int64)
    Rh, th = consensus_2p1p(
        np.random.default_rng(2).random((40, 4)), pb.arrays, ConsensusSettings(4.0, 3, 64, 1, 128), counters
    )
    assert len(Rh) >= 1 and counters[0] >= len(Rh)
    # The rotation is the two-point solver's, exact; the scale is the middle of the interval most
    # matches vote for, within a fraction of the threshold (tests/robust/test_consensus_scale.py).
    dc, dR = _closest(Rh, th, sc.query_pose)
    assert dc < 0.02 and dR < 1e-8


def test_landings_from_the_true_pose_stay_there_and_restarts_return_to_it(scene) -> None:
    sc = scene(14, num_refs=3, matches_per_pair=60, noise_px=0.0, outlier_ratio=0.0)
    pb = build_problem(sc.query_camera, sc.pairs)
    refiner = FinalRefiner(Planar2p1pEstimator(pb, RansacOptions()), RansacOptions())
    ref = refiner(sc.query_pose.R, sc.query_pose.t)
    assert np.linalg.norm(-ref.R.T @ ref.t - sc.query_pose.center) < 1e-9
    settings, rounds = refiner._budget(False)
    home = start_landings(
        ref.R[None], ref.t[None], sc.query_pose.center, ref.score, pb.arrays, settings, rounds
    )
    assert home.shape == (1, 2) and abs(home[0, 0]) < 1e-9 and home[0, 1] < 1e-9
    # 0.1 m along the weakest axis and back: noise-free, every match an inlier, one basin.
    out = restart_landings(ref.R, ref.t, ref.H, ref.score, 0.1, pb.arrays, settings, rounds)
    assert out.shape == (2, 2)
    assert np.all(np.abs(out[:, 0]) < 1e-6) and np.all(out[:, 1] < 1e-6)
    assert [(r.excess_cost, r.distance_m) for r in refiner.restarts(ref, 0.1)] == [tuple(x) for x in out]
    # No usable normal matrix: no restart.
    assert restart_landings(
        ref.R, ref.t, np.zeros((6, 6)), ref.score, 0.1, pb.arrays, settings, rounds
    ).shape == (0, 2)
