"""The final refinement of a search's pose: refined on its inliers until they stop changing.

With 2D-3D constraints and a map pose uncertainty the reference poses are refined too, as
nuisance parameters under the map prior (:mod:`planarloc.robust.map_prior`); otherwise the query
pose alone (:func:`planarloc.robust.refinement.refine_pose`, the paper's 2D-2D mode, whose
map-error share of the uncertainty is propagated afterwards).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.so3 import exp_so3
from planarloc.numerics.symmetric_eigen import symmetric_eigen
from planarloc.robust.estimators import ProblemEstimator
from planarloc.robust.map_prior import refine_with_map_prior
from planarloc.robust.options import RansacOptions
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.refinement import (
    RefineSettings,
    StartPose,
    centre_covariance,
    refine_pose_core,
    with_iterations,
)
from planarloc.robust.scoring import errors_sq

LATER_ROUND_ITERATIONS = 3  # LM iterations of the rounds after the first in refine_until_stable
FINAL_REFINEMENT_ROUNDS = 4  # inlier re-selections of the final refinement
FINAL_ITERATIONS = 6  # LM iterations of its first round
QUICK_ITERATIONS = 2  # a quick look: one round of this many iterations


@dataclass(frozen=True)
class RefinedPose:
    """One search's final pose: refined (R, t), centre covariance from the pixel noise, σ̂,
    robust cost, MSAC score at τ, the inlier masks at the pose, the 2D-3D share of the score and
    the refinement's (6, 6) normal matrix."""

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    sigma: float
    cost: float
    score: float
    in2d: np.ndarray
    in3d: np.ndarray
    score3d: float = 0.0
    H: np.ndarray | None = None


class StableRefinement(NamedTuple):
    """The result of :func:`refine_until_stable`: R (3, 3), t (3,), H (6, 6), σ̂ and the robust
    cost (as :class:`~planarloc.robust.refinement.Refinement`), the inlier masks in2d (N,), in3d
    (M,) at the returned pose, its MSAC cost ``Σ min(e², τ²)`` (the score every search is judged
    by) and the 2D-3D constraints' share of that cost."""

    R: np.ndarray
    t: np.ndarray
    H: np.ndarray
    sigma: float
    cost: float
    in2d: np.ndarray
    in3d: np.ndarray
    score: float
    score3d: float


@dataclass(frozen=True)
class FinalRefiner:
    """The final refinement of poses of one problem with one set of options.

    ``refiner(R, t, quick)`` refines a pose (:func:`refine_until_stable`; ``quick``: one round of
    ``QUICK_ITERATIONS``, a first look); :meth:`restarts` restarts it around a refined pose.
    ``scorer``: the estimator holding the flattened problem ``p`` and ``threshold_sq`` (τ², pixels²)."""

    scorer: ProblemEstimator
    options: RansacOptions

    def _budget(self, quick: bool) -> tuple[RefineSettings, int]:
        """The settings (LM iterations of the first round) and the rounds; no iterations when
        refinement is off."""
        iterations, rounds = (QUICK_ITERATIONS, 1) if quick else (FINAL_ITERATIONS, FINAL_REFINEMENT_ROUNDS)
        if not self.options.refine:
            iterations, rounds = 0, 1
        return self.scorer.refine_settings(iterations), rounds

    def __call__(self, R: np.ndarray, t: np.ndarray, quick: bool = False) -> RefinedPose:
        settings, rounds = self._budget(quick)
        R, t, H, sigma, cost, in2d, in3d, score, score3d = refine_until_stable(
            np.ascontiguousarray(R), np.ascontiguousarray(t), self.scorer.p.arrays, settings, rounds
        )
        return RefinedPose(R, t, centre_covariance(H, sigma), sigma, cost, score, in2d, in3d, score3d, H)

    def landings(self, R: np.ndarray, t: np.ndarray, ref: RefinedPose) -> list[Restart]:
        """Where full refinements started at the poses R (k, 3, 3), t (k, 3) land, relative to
        ``ref``: one :class:`Restart` per start (:func:`start_landings`, one compiled call)."""
        settings, rounds = self._budget(False)
        landed = start_landings(
            np.ascontiguousarray(R),
            np.ascontiguousarray(t),
            -ref.R.T @ ref.t,
            float(ref.score),
            self.scorer.p.arrays,
            settings,
            rounds,
        )
        return [Restart(float(e), float(d)) for e, d in landed]

    def restarts(self, ref: RefinedPose, step_m: float) -> list[Restart]:
        """Where restarts of the refinement around ``ref`` land: one :class:`Restart` per start
        (none when ``ref`` has no usable normal matrix).

        The starts are ``ref`` moved along ±v, the eigenvector of the smallest eigenvalue of its
        normal matrix H (6, 6) (the top one of the covariance ``σ̂² H⁻¹``: rotation and centre
        coupled as the data couple them), scaled so that the centre moves by ``step_m``. Each is
        refined in full like ``ref``. One that lands with an MSAC cost about ``ref.score`` (or
        below it), wherever it lands, is a pose the data support as well, and its distance a
        lower bound on the position's uncertainty: the curvature at ``ref`` sees only its own
        basin (benchmarks/robustness.py --protocol hard, seeds 1, 5, 7, 11, 21, 33, 60 %
        outliers: the true pose's basin lay 0.15-0.7 m away along v at a cost within the margin,
        and restarts landed between the two, inside the promise of a 0.04-0.1 m std, where they
        used to be ignored). :func:`planarloc.robust.rivals.basin_distance` sets the margins.
        One compiled call (:func:`restart_landings`): as Python around two compiled refinements
        it spent ~50 µs per query between them (benchmarks/estimator_profile.py, issue 31).
        """
        if ref.H is None:
            return []
        settings, rounds = self._budget(False)
        landed = restart_landings(
            np.ascontiguousarray(ref.R),
            np.ascontiguousarray(ref.t),
            np.ascontiguousarray(ref.H),
            float(ref.score),
            float(step_m),
            self.scorer.p.arrays,
            settings,
            rounds,
        )
        return [Restart(float(e), float(d)) for e, d in landed]


class Restart(NamedTuple):
    """Where one restart of the refinement landed: its MSAC cost above the refined pose's
    (pixels², negative when lower) and its centre's distance from the refined pose's (m)."""

    excess_cost: float
    distance_m: float


@njit(cache=True, error_model="numpy")
def refine_until_stable(
    Rq: np.ndarray, tq: np.ndarray, prob: ProblemArrays, settings: RefineSettings, rounds: int
) -> StableRefinement:
    """The final refinement: :func:`refine_pose` on the inliers of the current pose, repeated on
    the refined pose's inliers while they change (at most ``rounds`` times), in one call.

    Args:
        Rq, tq: the RANSAC winner ``query_from_world``.
        prob: the problem's arrays (:attr:`planarloc.robust.problem.AbsolutePoseProblem.arrays`).
        settings: τ² (pixels²) defining the inliers, the loss scale, the LM iterations of the
            first round (0: only evaluate H and the cost at the pose; later rounds take at most
            ``LATER_ROUND_ITERATIONS``), the σ̂ floor and the map prior: when either of its stds
            is > 0 and the problem has 2D-3D inliers, :func:`refine_with_map_prior` refines (H is
            then the marginal information of the query pose).
        rounds: at most this many refinements (≥ 1).
    """
    inlier_threshold_sq, max_iterations = settings.inlier_threshold_sq, settings.max_iterations
    R, t = Rq.copy(), tq.copy()
    e2d, e3d = errors_sq(R, t, prob)
    in2d = e2d < inlier_threshold_sq
    in3d = e3d < inlier_threshold_sq
    eye = np.eye(3)
    free = np.zeros(6, dtype=np.bool_)
    prior = settings.map_rotation_std_rad > 0.0 or settings.map_position_std_m > 0.0
    H = np.zeros((6, 6))
    sigma = np.inf
    cost = np.inf
    for rnd in range(max(rounds, 1)):
        # Later rounds start at an optimum whose inlier set changed by a few matches: a couple of
        # iterations reach the new one (the first round may start a few pixels away).
        its = max_iterations if rnd == 0 else min(max_iterations, LATER_ROUND_ITERATIONS)
        round_settings = with_iterations(settings, its)
        start = StartPose(R, -m3.t_vec(R, t), eye, free)
        idx2d, idx3d = np.flatnonzero(in2d), np.flatnonzero(in3d)
        if prior and in3d.any():
            R, t, H, sigma, cost = refine_with_map_prior(start, prob, idx2d, idx3d, round_settings)
        else:
            R, t, H, sigma, cost = refine_pose_core(start, prob, idx2d, idx3d, round_settings, np.bool_(True))
        e2d, e3d = errors_sq(R, t, prob)
        new2d = e2d < inlier_threshold_sq
        new3d = e3d < inlier_threshold_sq
        same = np.array_equal(new2d, in2d) and np.array_equal(new3d, in3d)
        in2d, in3d = new2d, new3d
        if same:
            break
    msac2d = 0.0
    for i in range(e2d.shape[0]):
        msac2d += min(e2d[i], inlier_threshold_sq)
    msac3d = 0.0
    for i in range(e3d.shape[0]):
        msac3d += min(e3d[i], inlier_threshold_sq)
    return StableRefinement(R, t, H, sigma, cost, in2d, in3d, msac2d + msac3d, msac3d)


@njit(cache=True, error_model="numpy")
def start_landings(
    Rs: np.ndarray,
    ts: np.ndarray,
    c: np.ndarray,
    score: float,
    prob: ProblemArrays,
    settings: RefineSettings,
    rounds: int,
) -> np.ndarray:
    """Where refinements started at ``(Rs (k, 3, 3), ts (k, 3))`` land (:func:`refine_until_stable`
    with ``prob``, ``settings``, ``rounds``): (k, 2), per start the landing's MSAC cost above
    ``score`` (pixels²) and its centre's distance from ``c`` (3,) (m)."""
    out = np.empty((Rs.shape[0], 2))
    for k in range(Rs.shape[0]):
        landed = refine_until_stable(
            np.ascontiguousarray(Rs[k]), np.ascontiguousarray(ts[k]), prob, settings, rounds
        )
        d = -m3.t_vec(landed.R, landed.t) - c
        out[k, 0] = landed.score - score
        out[k, 1] = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return out


@njit(cache=True, error_model="numpy")
def restart_landings(
    R: np.ndarray,
    t: np.ndarray,
    H: np.ndarray,
    score: float,
    step_m: float,
    prob: ProblemArrays,
    settings: RefineSettings,
    rounds: int,
) -> np.ndarray:
    """Where the restarts of :meth:`FinalRefiner.restarts` land, in one call.

    Args:
        R, t: the refined pose ``query_from_world`` (3, 3), (3,); H: its (6, 6) normal matrix;
            score: its MSAC cost.
        step_m: how far the starts move the centre (metres).
        prob, settings, rounds: as :func:`refine_until_stable` refines.

    Returns:
        :func:`start_landings` of the starts along +v, then −v; (0, 2) when H has no positive
        smallest eigenvalue or its eigenvector does not move the centre.
    """
    w, V = np.empty(6), np.empty((6, 6))
    if not symmetric_eigen(H, w, V) or not w[0] > 0.0:
        return np.empty((0, 2))
    nc = np.sqrt(V[3, 0] * V[3, 0] + V[4, 0] * V[4, 0] + V[5, 0] * V[5, 0])
    if not nc > 1e-12:
        return np.empty((0, 2))
    c = -m3.t_vec(R, t)
    Rs, ts = np.empty((2, 3, 3)), np.empty((2, 3))
    step = np.empty(6)
    for s in range(2):
        scale = (1.0 if s == 0 else -1.0) * (step_m / nc)
        for k in range(6):
            step[k] = scale * V[k, 0]
        R0 = m3.mul(exp_so3(step[:3]), R)
        m3.store_pose(Rs, ts, s, R0, -m3.vec(R0, c + step[3:]))
    return start_landings(Rs, ts, c, score, prob, settings, rounds)
