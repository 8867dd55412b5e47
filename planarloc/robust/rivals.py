"""Rival answers: other poses that explain the matches about as well as a judged one.

A rival far from a pose bounds its position std from below: the runner-ups of its search (its
locally optimised models, :func:`rival_distance`; its raw hypotheses, refined in full,
:func:`pool_basins`), a restart of its refinement that falls into another basin of the cost
(:func:`basin_distance`), and another search's pose found after the judgement
(:func:`with_rival`). :mod:`planarloc.robust.verification` applies them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.robust.final_refinement import FinalRefiner, RefinedPose, Restart
from planarloc.robust.options import RansacOptions
from planarloc.robust.ransac import ALTERNATIVE_MARGIN_INLIERS
from planarloc.robust.result import PoseEstimate
from planarloc.robust.status import Status

# Another search's refined pose within this ratio of the best MSAC cost is a rival answer
# (planarloc.robust.absolute_pose compares the searches).
RIVAL_COST_RATIO = 1.25
MAX_ALTERNATIVE_REFINEMENTS = 2  # runner-up hypotheses refined per verified pose
# A runner-up within this many inliers' worth of MSAC cost is a rival. 2, not more: at 3 x 20
# matches / 60 % outliers a margin of 4 removed 6 of 8 broken promises of 2p1p but refused 9 % of
# its correct poses (and the oracle's); 2 removes half of them at a cost of 1-3 points.
RIVAL_MARGIN_INLIERS = ALTERNATIVE_MARGIN_INLIERS // 2
# For a pose on fewer inliers than this, a restart landing within NEAR_BASIN_MARGIN_INLIERS widens
# the std (:func:`basin_distance`): that is where benchmarks/robustness.py --protocol hard found
# successes 0.2-3 m off with std 0.04-0.2 m (3 references x 20 matches, 12-31 inliers); the paper
# protocol's 40-200 inliers had none.
NEAR_BASIN_BELOW_INLIERS = 32
# A restart of the refinement beyond the promise is a rival when it explains the matches within
# one inlier's worth of cost (or better): the other basins of weak data are where the checks
# refused most correct poses of the hard protocol (3 x 20 matches, 60 % outliers) at two.
RESTART_MARGIN_INLIERS = 1
# For a pose on fewer than NEAR_BASIN_BELOW_INLIERS inliers, a restart landing within this many
# inliers' worth of cost widens the std to its distance, up to the largest std of a success,
# without refusing the pose: with so few inliers, a pose that absorbs a few outliers is barely
# told apart from the truth.
NEAR_BASIN_MARGIN_INLIERS = 4
# Runner-up hypotheses of a weak pose's search refined in full to see where they land
# (:func:`pool_basins`).
POOL_BASIN_STARTS = 4
# ... for a pose on fewer inliers than this. Not NEAR_BASIN_BELOW_INLIERS: on the hard protocol's
# 50-match cells (40-60 % outliers) poses on 32-63 inliers broke promises the same way, a basin
# the search had drawn a hypothesis in, 1-4 inliers' worth above the answer. Seeds 102-133 (64,000
# scenes): broken promises of ``auto`` 28 -> 19, seeds above 0.1 % 8 -> 3, 19 correct poses fewer,
# +3.6 % time; 96 gave the same 19 for +5 % (BENCHMARKS.md, "Runner-ups' basins on more inliers").
POOL_BASINS_BELOW_INLIERS = 64


def rival_distance(
    estimator,
    ref: RefinedPose,
    alternatives: Sequence[tuple[np.ndarray, np.ndarray, float]],
    refine: Callable[[np.ndarray, np.ndarray, bool], RefinedPose],
    beyond: float,
) -> float:
    """Largest distance (> ``beyond``) from ``ref``'s centre of a refined runner-up that explains
    the matches as well as ``ref`` but for ``RIVAL_MARGIN_INLIERS`` inliers' worth of MSAC cost
    (``score − ref.score ≤ margin·τ²``); 0 if none.

    The margin is in inliers, not a cost ratio: with hundreds of inliers a pose 20 % worse is
    clearly worse, with twenty it may differ by three matches. The runner-ups are the search's
    other locally optimised models ``alternatives`` ``(R, t, MSAC cost)`` (free: their cost is
    known). Those lying beyond with a cost within twice the margin are refined, at most
    ``MAX_ALTERNATIVE_REFINEMENTS``. The search's raw hypotheses are :func:`pool_basins`' to
    examine: looking at them here too (for poses on fewer than 32 inliers, up to 2 of them, a
    quick look first) refused 99 more successes on 67 seeds of benchmarks/robustness.py
    --protocol hard (134,000 scenes), 55 of them correct, and kept no promise more
    (BENCHMARKS.md, "One examination of the search's runner-ups")."""
    margin = RIVAL_MARGIN_INLIERS * estimator.threshold_sq
    # Plain Python until a candidate is close enough in cost: this runs for every estimate.
    candidates = [a for a in alternatives if a[2] - ref.score <= 2.0 * margin]
    if not candidates:
        return 0.0
    c = -ref.R.T @ ref.t
    tried, found = 0, 0.0
    for R, t, cost in sorted(candidates, key=lambda a: a[2]):
        if tried == MAX_ALTERNATIVE_REFINEMENTS:
            break
        if np.linalg.norm(-R.T @ t - c) <= beyond:
            continue
        tried += 1
        alt = refine(R, t, True)  # a quick look first: most runner-ups settle clearly worse or back home
        d = float(np.linalg.norm(-alt.R.T @ alt.t - c))
        if alt.score - ref.score > 2.0 * margin or d <= beyond:
            continue
        alt = refine(R, t, False)
        d = float(np.linalg.norm(-alt.R.T @ alt.t - c))
        if alt.score - ref.score <= margin and d > beyond:
            found = max(found, d)
    return found


def with_rival(est: PoseEstimate, rival_centre: np.ndarray, options: RansacOptions) -> PoseEstimate:
    """A verified estimate checked against one more rival answer (another search's pose of about
    the same cost, found after the verification): the distance bounds the std from below; beyond
    ``max_position_std_m`` the estimate becomes ``ambiguous_pose``. The same rule as the rivals
    :func:`~planarloc.robust.verification.judge_pose` is given, without judging the pose again
    (an estimate without a pose is returned as it is)."""
    if est.pose is None:
        return est
    d = float(np.linalg.norm(np.asarray(rival_centre) - est.pose.center))
    if not d > est.position_std_m:
        return est
    if d > options.max_position_std_m:
        return PoseEstimate(
            None,
            False,
            Status.AMBIGUOUS_POSE,
            f"another search's pose {d:.3g} m away explains the matches "
            f"nearly as well (MSAC cost within {100 * (RIVAL_COST_RATIO - 1):.0f} %): the data do not "
            "single out one position; more matches or map images",
            est.inliers,
            est.num_inliers,
            est.num_inliers_3d,
            est.iterations,
            d,
            est.pose,
            est.stats,
            model=est.model,
        )
    scale = d / est.position_std_m
    cov = None if est.covariance is None else est.covariance.copy()
    if cov is not None:
        cov[:3, :] *= scale
        cov[:, :3] *= scale
    return dataclasses.replace(
        est,
        position_std_m=d,
        covariance=cov,
        message=est.message.replace(f"position std {est.position_std_m:.3g} m", f"position std {d:.3g} m"),
    )


class BasinRivals(NamedTuple):
    """Restarts of the refinement that landed in other basins (:func:`basin_distance`).

    Attributes:
        rival_m: the farthest within :data:`RESTART_MARGIN_INLIERS` inlier's worth of cost (or
            below it), wherever it landed: a rival answer (0: none).
        near_m: for a pose on few inliers, the farthest within :data:`NEAR_BASIN_MARGIN_INLIERS`
            inliers' worth and no farther than the largest std a success may have: a basin the
            data barely tell apart, which widens the std without refusing the pose (0: none).
    """

    rival_m: float
    near_m: float


def basin_distance(
    estimator, ref: RefinedPose, refine: FinalRefiner, step_m: float, num_inliers: int, max_std_m: float
) -> BasinRivals:
    """The poses that explain the matches about as well, found by restarting the refinement
    ``step_m`` away (just outside the promise) along the weakest axis of the pose covariance;
    the std is then at least their distance, wherever they lie.

    The refinement re-selects its inliers, so a restart can fall into a basin with another
    inlier set, which the curvature at ``ref`` cannot know about. The start is ``ref`` moved
    along ±v, the top eigenvector of ``σ̂² H⁻¹`` (rotation and centre coupled as the data
    couple them: a distant scene trades rotation for translation), scaled so that the centre
    moves by ``step_m``. A restart that lands with an MSAC cost within
    ``RESTART_MARGIN_INLIERS`` inlier's worth of ``ref``'s (or lower) is another answer the data
    support as well: beyond the promise it is a rival basin, inside it a flat valley the
    curvature does not see (both broke promises on the hard protocol). The restarts take the
    full refinement, not a quick look: falling into another basin takes the rounds of inlier
    re-selection (a quick look missed a facade pose 0.5 m off with a 0.14 m std)
    (:meth:`FinalRefiner.restarts`).

    For a pose on fewer than :data:`NEAR_BASIN_BELOW_INLIERS` inliers (``num_inliers``), one
    landing within :data:`NEAR_BASIN_MARGIN_INLIERS` inliers' worth and within ``max_std_m``
    widens the std only (:attr:`BasinRivals.near_m`). benchmarks/robustness.py --protocol hard,
    seeds 1, 5, 7, 11, 21, 33 (12,000 scenes): 10 successes broke their promise, 9 of them on
    20-28 inliers; the true pose lay along the restarts' axis (cosine 0.85-1.0), and for 5 of
    them a restart landed next to it, 0.13-0.25 m away at 1.4-3.5 inliers' worth of cost above
    the answer, where the 1-inlier margin ignored it.
    """
    return _landings(
        estimator, refine.restarts(ref, step_m), num_inliers < NEAR_BASIN_BELOW_INLIERS, max_std_m
    )


def pool_basins(
    estimator,
    ref: RefinedPose,
    pool: tuple[np.ndarray, np.ndarray],
    refine: FinalRefiner,
    std_m: float,
    promise_m: float,
    num_inliers: int,
    max_std_m: float,
) -> BasinRivals:
    """Where the search's runner-up hypotheses of a weak pose land when refined: the basins of
    :func:`basin_distance`, started from where the search itself looked (nothing for a pose on
    :data:`POOL_BASINS_BELOW_INLIERS` inliers or more; ``num_inliers`` counts the pose's).

    The restarts go along the weakest axis of the curvature at ``ref`` only; on few inliers the
    truth's basin may lie along another (a pose that absorbed outliers bends the cost), and the
    search often drew a hypothesis next to it that lost on raw cost to one the local optimisation
    then took elsewhere. Its raw cost says little about its basin (3-18 px² above it in the
    hard protocol's broken promises, often beyond :func:`rival_distance`'s margin), so up to
    :data:`POOL_BASIN_STARTS` of the raw hypotheses ``pool`` (R (k, 3, 3), t (k, 3)) are
    refined in full, cheapest first, skipping those within ``std_m`` of ``ref``'s centre or of
    a start already taken (they would land at home; :func:`pool_starts`), in one compiled call
    (:meth:`~planarloc.robust.final_refinement.FinalRefiner.landings`). Where they land is
    judged as the restarts' landings are (:func:`_landings`), but for one landing within
    ``promise_m`` (3σ + 5 cm) at about ``ref``'s cost: that is the pose's own valley, which
    widens its std as a near basin does rather than refusing it (as a rival there, the same
    scenes lost 0.05 points more of correct poses for no promise more).
    benchmarks/robustness.py --protocol hard, seeds 94-109 (32,000 scenes new to the estimator):
    broken promises of ``auto`` 25 -> 18, success at 0.1 m / 1° within 0.11 points
    (BENCHMARKS.md, "Runner-ups' basins, and what fresh seeds say"), then 28 -> 19 on seeds
    102-133 when poses on 32-63 inliers were examined too (:data:`POOL_BASINS_BELOW_INLIERS`).
    This is the one examination of the raw hypotheses (:func:`rival_distance` looks at the locally
    optimised ones).
    """
    R, t = pool
    if num_inliers >= POOL_BASINS_BELOW_INLIERS or not len(R):
        return BasinRivals(0.0, 0.0)
    full, _ = estimator.score(R, t)
    starts = pool_starts(
        np.ascontiguousarray(R), np.ascontiguousarray(t), np.argsort(full), -ref.R.T @ ref.t, std_m
    )
    # Every pose examined here is weak: the near rule holds over the whole reach.
    return _landings(estimator, refine.landings(R[starts], t[starts], ref), True, max_std_m, promise_m)


@njit(cache=True, error_model="numpy")
def pool_starts(R: np.ndarray, t: np.ndarray, order: np.ndarray, c: np.ndarray, std_m: float) -> np.ndarray:
    """The starts :func:`pool_basins` refines: in ``order`` (cheapest first), the hypotheses
    ``query_from_world`` R (k, 3, 3), t (k, 3) whose centre lies farther than ``std_m`` from ``c``
    (3,) and from every start taken before, at most :data:`POOL_BASIN_STARTS` (indices)."""
    centres = np.empty((R.shape[0], 3))
    for n in range(R.shape[0]):
        centre = -m3.t_vec(R[n], t[n])
        for k in range(3):
            centres[n, k] = centre[k]
    starts = np.empty(POOL_BASIN_STARTS, dtype=np.int64)
    taken = 0
    for i in order:
        if _distance(centres[i], c) <= std_m:
            continue
        if _any_within(centres, starts[:taken], centres[i], std_m):
            continue
        starts[taken] = i
        taken += 1
        if taken == POOL_BASIN_STARTS:
            break
    return starts[:taken]


@njit(cache=True, inline="always")
def _distance(a: np.ndarray, b: np.ndarray) -> float:
    return np.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


@njit(cache=True, inline="always")
def _any_within(centres: np.ndarray, rows: np.ndarray, x: np.ndarray, radius: float) -> bool:
    """Whether any of ``centres[rows]`` lies within ``radius`` of ``x``."""
    for r in rows:
        if _distance(centres[r], x) <= radius:
            return True
    return False


def _landings(
    estimator, landed: Sequence[Restart], weak: bool, max_std_m: float, rival_beyond_m: float = 0.0
) -> BasinRivals:
    """Refinements started away from a pose, judged by where they landed (:class:`Restart`): one
    within :data:`RESTART_MARGIN_INLIERS` inlier's worth of its cost (or below) and farther than
    ``rival_beyond_m`` is a rival; for a ``weak`` pose (few inliers, as the caller counts them),
    one within :data:`NEAR_BASIN_MARGIN_INLIERS` inliers' worth and ``max_std_m`` widens the std
    only."""
    tight = RESTART_MARGIN_INLIERS * estimator.threshold_sq
    near = NEAR_BASIN_MARGIN_INLIERS * estimator.threshold_sq if weak else tight
    rival_m = near_m = 0.0
    for r in landed:
        if r.excess_cost <= tight and r.distance_m > rival_beyond_m:
            rival_m = max(rival_m, r.distance_m)
        elif r.excess_cost <= near and r.distance_m <= max_std_m:
            near_m = max(near_m, r.distance_m)
    return BasinRivals(rival_m, near_m)
