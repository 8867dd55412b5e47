"""Judging a refined pose: its uncertainty, the verification checks, the status it earns.

:mod:`planarloc.robust.observability` computes what the matches can tell about a pose (support,
collinearity, map-error propagation, leave-one-reference-out spread, planar fit); this module
turns those numbers into the promise of a :class:`PoseEstimate`: a ``success`` only for a pose
whose position std (linearised covariance inflated for correlated residuals, map errors,
profile along weak directions, rival answers, jackknife spread) is within
``max_position_std_m`` and that every check passes; otherwise a failure status that says why.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from planarloc.geometry.mat3 import sym_eigvals
from planarloc.geometry.pose import Pose
from planarloc.numerics.cholesky import cholesky_factor, spd_inverse
from planarloc.robust import observability as obs
from planarloc.robust.chance_support import beyond_chance, chance_inliers
from planarloc.robust.final_refinement import FinalRefiner, RefinedPose
from planarloc.robust.options import RansacOptions, Structure
from planarloc.robust.planar_scene import distant_planar_pairs
from planarloc.robust.problem import AbsolutePoseProblem
from planarloc.robust.ransac import ALTERNATIVE_MARGIN_INLIERS
from planarloc.robust.refinement import centre_covariance
from planarloc.robust.result import PoseEstimate, RansacStatistics
from planarloc.robust.status import Status

PROFILE_BELOW_RATIO = 0.15  # centre collinearity ratio under which the cost profile is checked
PROFILE_BELOW_INLIERS = 400  # fewer inliers than this: restarts look for other basins of the cost
# Another search's refined pose within this ratio of the best MSAC cost is a rival answer
# (planarloc.robust.absolute_pose compares the searches).
RIVAL_COST_RATIO = 1.25
# Homography transfer tolerance in units of the epipolar threshold (both keypoints are noisy).
PLANAR_TRANSFER_SCALE = 2.0
MAX_ALTERNATIVE_REFINEMENTS = 2  # runner-up hypotheses refined per verified pose
# A runner-up within this many inliers' worth of MSAC cost is a rival. 2, not more: at 3 x 20
# matches / 60 % outliers a margin of 4 removed 6 of 8 broken promises of 2p1p but refused 9 % of
# its correct poses (and the oracle's); 2 removes half of them at a cost of 1-3 points.
RIVAL_MARGIN_INLIERS = ALTERNATIVE_MARGIN_INLIERS // 2
# Raw runner-up hypotheses are examined too for poses on fewer inliers than this: that is where
# benchmarks/robustness.py --protocol hard found successes 0.2-3 m off with std 0.04-0.2 m (3
# references x 20 matches, 12-31 inliers); the paper protocol's 40-200 inliers had none.
RIVAL_POOL_BELOW_INLIERS = 32
# A restart of the refinement beyond the promise is a rival when it explains the matches within
# one inlier's worth of cost (or better): the other basins of weak data are where the checks
# refused most correct poses of the hard protocol (3 x 20 matches, 60 % outliers) at two.
RESTART_MARGIN_INLIERS = 1
MAX_POOL_CANDIDATES = 8


def _rival_distance(
    estimator,
    ref: RefinedPose,
    num_inliers: int,
    alternatives: Sequence[tuple[np.ndarray, np.ndarray, float]],
    pool: tuple[np.ndarray, np.ndarray],
    refine: Callable[[np.ndarray, np.ndarray, bool], RefinedPose],
    beyond: float,
) -> float:
    """Largest distance (> ``beyond``) from ``ref``'s centre of a refined runner-up that explains
    the matches as well as ``ref`` but for ``RIVAL_MARGIN_INLIERS`` inliers' worth of MSAC cost
    (``score − ref.score ≤ margin·τ²``); 0 if none.

    The margin is in inliers, not a cost ratio: with hundreds of inliers a pose 20 % worse is
    clearly worse, with twenty it may differ by three matches. Runner-ups are the search's
    other locally optimised models ``alternatives`` ``(R, t, MSAC cost)`` (free: their cost is
    known), and, for a pose resting on fewer than ``RIVAL_POOL_BELOW_INLIERS`` inliers, the
    search's raw hypotheses near its best cost (``pool``; rescored in full). Those lying beyond
    with a cost within twice the margin are refined, at most ``MAX_ALTERNATIVE_REFINEMENTS``."""
    margin = RIVAL_MARGIN_INLIERS * estimator.threshold_sq
    # Plain Python until a candidate is close enough in cost: this runs for every estimate.
    candidates = [a for a in alternatives if a[2] - ref.score <= 2.0 * margin]
    if num_inliers < RIVAL_POOL_BELOW_INLIERS and len(pool[0]):
        full, _ = estimator.score(*pool)
        order = np.argsort(full)
        candidates += [
            (pool[0][i], pool[1][i], float(full[i]))
            for i in order[:MAX_POOL_CANDIDATES]
            if full[i] - ref.score <= 2.0 * margin
        ]
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
    :func:`judge_pose` is given, without judging the pose again."""
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


def _position_covariance(
    estimator, options: RansacOptions, ref: RefinedPose, support: obs.PoseSupport, correlation: float
) -> np.ndarray:
    """(3, 3) position covariance of a refined pose, from every source of error.

    * pixel noise, ``σ̂² H⁻¹``, inflated by ``correlation`` (residuals within one reference are
      correlated: its pose error, calibration, model errors);
    * the map's pose errors: with 2D-3D inliers the final refinement estimated the reference
      poses under the map prior (:mod:`planarloc.robust.map_prior`), so H holds their share of
      the 2D-2D constraints; in the 2D-2D mode they are propagated through the full model
      (weak geometry amplifies them: a 0.1° error of a reference's rotation moves a 2D-2D
      position by metres when the query is almost collinear with the references). Never less
      than the references' own error moved rigidly with the query (triangulated points inherit
      it: KITTI, tracks, 95 % -> 100 % of successes within 3σ + 5 cm with it), averaged over the
      supporting references when the map prior was measured (independent per image) and
      2D-3D constraints carry the pose;
    * the 2D-3D points' own uncertainty (far points seen at a small angle are uncertain in
      depth; a query seen from elsewhere inherits that, and over few points it does not
      average out like pixel noise).
    """
    cov = ref.cov * correlation**2
    if not np.isfinite(cov).all():
        return cov
    n3d = int(np.count_nonzero(ref.in3d))
    rotation_std, position_std = _map_prior(options, n3d)
    if rotation_std > 0 or position_std > 0:
        if n3d == 0:
            cov = cov + obs.map_covariance(
                estimator, ref.R, ref.t, ref.in2d, ref.in3d, (rotation_std, position_std)
            )
        rigid = position_std**2 + (support.median_distance_m * math.radians(rotation_std)) ** 2
        if options.map_prior_measured and n3d >= options.min_inliers:
            # Measured per-image errors are independent: the query inherits their mean over the
            # supporting references, not each one whole.
            rigid /= max(len(support.supporting), 1)
        cov = cov + np.eye(3) * rigid
    if n3d and ref.H is not None:
        cov = cov + obs.points_covariance(estimator, ref.R, ref.t, ref.in3d, ref.H)
    return cov


def _map_prior(options: RansacOptions, n3d: int) -> tuple[float, float]:
    """The map stds (degrees, metres) a pose with ``n3d`` 2D-3D inliers propagates: the options',
    raised to the assumed prior for a pose on 2D-2D constraints alone when the options' were
    measured (a small measured prior does not make wrong-but-consistent 2D-2D matches precise:
    fountain_p11's map measured 0.002°, and an entry_p10 query 0.98 m off got a 0.09 m std)."""
    rotation, position = options.map_rotation_std_deg, options.map_position_std_m
    if options.map_prior_measured and n3d < options.min_inliers and options.assumed_map_prior is not None:
        rotation, position = (
            max(rotation, options.assumed_map_prior[0]),
            max(position, options.assumed_map_prior[1]),
        )
    return rotation, position


def pose_covariance(
    ref: RefinedPose, position_cov: np.ndarray, std: float, correlation: float, options: RansacOptions
) -> np.ndarray | None:
    """(6, 6) covariance of ``world_from_camera`` in ROS order (centre x y z, rotation vector about
    the world axes; :attr:`PoseEstimate.covariance`).

    The refinement's ``σ̂² H⁻¹`` (parameters ``δ``, the rotation increment in the camera frame,
    ``R_cw' = Exp(δ) R_cw``, and the centre) inflated by ``correlation``; its rotation block gets
    the map's rotation error as a floor. ``world_from_camera`` rotates by ``φ = −R_cwᵀ δ``. The
    position block is replaced by ``position_cov`` (every source of error) scaled so that its
    largest eigenvalue is ``std²`` (the checks may have raised the std), the cross terms scaled
    alike. None when H is singular or the position covariance is not positive.
    """
    if ref.H is None or not (np.isfinite(ref.H).all() and np.isfinite(position_cov).all()):
        return None
    out = np.empty((6, 6))
    status = _pose_covariance_kernel(
        np.ascontiguousarray(ref.H),
        ref.sigma * correlation,
        ref.R,
        np.ascontiguousarray(position_cov),
        std,
        math.radians(options.map_rotation_std_deg) ** 2,
        out,
    )
    if status == 0:
        return None
    if status == 2:  # not positive definite after the replacement: clip the eigenvalues
        w, V = np.linalg.eigh(out)
        return (V * np.maximum(w, 1e-18)) @ V.T
    return out


@njit(cache=True, error_model="numpy")
def _pose_covariance_kernel(
    H: np.ndarray,
    noise: float,
    R: np.ndarray,
    position_cov: np.ndarray,
    std: float,
    rotation_var: float,
    out: np.ndarray,
) -> int:
    """:func:`pose_covariance` into ``out`` (6, 6): 0 if H (6, 6) is singular or the position
    covariance (3, 3) not positive, 2 if ``out`` is not positive definite, else 1. ``noise``:
    σ̂ times the correlation inflation; ``rotation_var``: the map's rotation variance (rad²).
    One compiled call: the numpy version spent ~70 µs on a dozen 6 x 6 calls per estimate."""
    C = np.empty((6, 6))
    if not spd_inverse(H, C, 0.0):
        return 0
    lam = sym_eigvals(position_cov)[0]
    if not lam > 0.0:
        return 0
    gain = max(1.0, std * std / lam)
    trace_pos, trace_c = 0.0, 0.0
    for i in range(3):
        trace_pos += position_cov[i, i] * gain
        trace_c += C[3 + i, 3 + i] * noise * noise
    scale = np.sqrt(max(trace_pos / max(trace_c, 1e-300), 0.0))
    # J = diag(−Rᵀ, I) maps (δ, c) to (φ, c): rotation block −Rᵀ C_δδ (−Rᵀ)ᵀ, cross block C_cδ (−Rᵀ)ᵀ.
    for i in range(3):
        for j in range(3):
            out[i, j] = position_cov[i, j] * gain
            rot, cross = 0.0, 0.0
            for a in range(3):
                cross -= C[3 + i, a] * R[a, j]
                for b in range(3):
                    rot += R[a, i] * C[a, b] * R[b, j]
            out[3 + i, 3 + j] = rot * noise * noise + (rotation_var if i == j else 0.0)
            out[i, 3 + j] = cross * noise * noise * scale
    for i in range(3):
        for j in range(3):
            out[3 + j, i] = out[i, 3 + j]
    for i in range(6):  # symmetric to rounding
        for j in range(i + 1, 6):
            out[i, j] = out[j, i] = 0.5 * (out[i, j] + out[j, i])
    L = np.empty((6, 6))
    return 1 if cholesky_factor(out, L, 0.0) else 2


def _basin_distance(estimator, ref: RefinedPose, refine: FinalRefiner, beyond: float) -> float:
    """Distance (> ``beyond``) of another basin of the cost found by restarting the refinement
    just outside the promise, along the weakest axis of the pose covariance; 0 if none.

    The refinement re-selects its inliers, so a restart can fall into a basin with another
    inlier set, which the curvature at ``ref`` cannot know about. The start is ``ref`` moved
    along ±v, the top eigenvector of ``σ̂² H⁻¹`` (rotation and centre coupled as the data
    couple them: a distant scene trades rotation for translation), scaled so that the centre
    moves by ``beyond``. A restart that lands beyond ``beyond`` with an MSAC cost within
    ``RESTART_MARGIN_INLIERS`` inlier's worth of ``ref``'s (or lower) is another answer the data
    support as well. The restarts take the full refinement, not a quick look: falling into
    another basin takes the rounds of inlier re-selection (a quick look missed a facade pose
    0.5 m off with a 0.14 m std) (:meth:`FinalRefiner.restart_distance`).
    """
    return refine.restart_distance(ref, beyond, RESTART_MARGIN_INLIERS * estimator.threshold_sq)


def split_by_pair(mask: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    """(N,) mask over all matches -> one (N_p,) mask per pair (views of ``mask``)."""
    bounds = offsets.tolist()
    return [mask[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


def failed_estimate(
    problem: AbsolutePoseProblem, stats: RansacStatistics, t_start: float, status: Status, message: str, **kw
) -> PoseEstimate:
    """A :class:`PoseEstimate` without a pose (``kw``: inliers, counts, std, unreliable_pose, model)."""
    stats.time_s["total"] = time.perf_counter() - t_start  # elapsed, set: a pose may be judged twice
    inliers = kw.pop("inliers", None)
    if inliers is None:
        inliers = split_by_pair(np.zeros(len(problem.xq), dtype=bool), problem.offsets)
    return PoseEstimate(None, False, status, message, inliers, iterations=stats.iterations, stats=stats, **kw)


@dataclass(frozen=True)
class EstimateContext:
    """What one estimate fixes for every pose it judges: the problem, the options, gravity
    ((3,) unit vectors down, in the world and in the query frame), the statistics (times are
    added) and ``t_start``, the estimate's ``perf_counter`` start (for the total time)."""

    problem: AbsolutePoseProblem
    options: RansacOptions
    gravity_world: np.ndarray
    query_gravity: np.ndarray
    stats: RansacStatistics
    t_start: float


@dataclass(frozen=True)
class Candidate:
    """A search's refined pose and what a verifier may inspect of its search.

    Attributes:
        estimator: the scoring estimator of the problem (its matches, options, refinement).
        ref: the search's refined pose.
        alternatives: the search's other locally optimised models ``(R, t, MSAC cost)``.
        pool: its raw hypotheses near the best cost ``(R (k, 3, 3), t (k, 3))``.
        refine: the search's :class:`FinalRefiner`; ``refine(R, t, quick)`` refines one like
            ``ref`` (``quick``: one round of two iterations, a first look). None: no runner-up
            is examined.
        any_plane_degenerate: the search's solver cannot tell the epipolar geometry on a plane
            (the 8-point algorithm): any plane, not only a distant one, is degenerate.
    """

    estimator: object
    ref: RefinedPose
    alternatives: Sequence[tuple[np.ndarray, np.ndarray, float]] = ()
    pool: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    refine: FinalRefiner | None = None
    any_plane_degenerate: bool = False


@dataclass
class _Judging:
    """A pose under judgement: its evidence and the std the checks raise as they go."""

    ctx: EstimateContext
    cand: Candidate
    t0: float
    support: obs.PoseSupport
    correlation: float
    cov: np.ndarray
    std: float
    linear_std: float
    rival: float
    pose: Pose
    model: str
    inliers: list[np.ndarray]
    n2d: int
    n3d: int

    def fail(self, status: Status, message: str, with_pose: bool = True) -> PoseEstimate:
        """The failed estimate (the pose as ``unreliable_pose`` when ``with_pose``)."""
        ctx = self.ctx
        ctx.stats.add_time("verification", time.perf_counter() - self.t0)
        kw = dict(unreliable_pose=self.pose) if with_pose else {}
        return failed_estimate(
            ctx.problem,
            ctx.stats,
            ctx.t_start,
            status,
            message,
            position_std_m=self.std,
            inliers=self.inliers,
            num_inliers=self.n2d,
            num_inliers_3d=self.n3d,
            model=self.model,
            **kw,
        )


def judge_pose(ctx: EstimateContext, cand: Candidate, rivals: Sequence[np.ndarray] = ()) -> PoseEstimate:
    """Uncertainty and verification of a refined pose; a ``success`` only if it passes.

    Args:
        ctx: the estimate's problem, options, gravity and statistics.
        cand: the search's refined pose and its runner-ups. A runner-up that refines to a pose
            beyond ``3·std + 5 cm`` explaining the matches as well but for
            ``RIVAL_MARGIN_INLIERS`` inliers is a rival answer (:func:`_rival_distance`): the
            distance bounds the std from below (``ambiguous_pose`` when that exceeds the limit).
        rivals: (3,) centres of other searches' refined poses of nearly the same cost.

    Returns:
        :class:`PoseEstimate`: ``success`` with the position std, or the first failed check as
        its status (``too_few_inliers``, ``single_reference``, ``degenerate_scale``,
        ``inconsistent_references``, ``ambiguous_pose``) with the pose as ``unreliable_pose``
        where one exists.
    """
    j = _uncertainty(ctx, cand, rivals, time.perf_counter())
    for check in (_check_support, _check_distant_plane, _check_position, _check_runner_ups):
        failed = check(j)
        if failed is not None:
            return failed
    stats, std = ctx.stats, j.std
    stats.add_time("verification", time.perf_counter() - j.t0)
    stats.time_s["total"] = time.perf_counter() - ctx.t_start  # elapsed, set: a pose may be judged twice
    covariance = pose_covariance(cand.ref, j.cov, std, j.correlation, ctx.options)
    return PoseEstimate(
        j.pose,
        True,
        Status.SUCCESS,
        f"{j.n2d} 2D-2D and {j.n3d} 2D-3D inliers, position std {std:.3g} m, {j.model} model",
        j.inliers,
        j.n2d,
        j.n3d,
        stats.iterations,
        std,
        None,
        stats,
        model=j.model,
        covariance=covariance,
    )


def _uncertainty(ctx: EstimateContext, cand: Candidate, rivals: Sequence[np.ndarray], t0: float) -> _Judging:
    """The pose's support and position std: the linearised covariance, inflated for correlated
    residuals, profiled along weak directions of near-collinear geometry, bounded by rivals."""
    options, estimator, ref = ctx.options, cand.estimator, cand.ref
    R, t, in2d, in3d = ref.R, ref.t, ref.in2d, ref.in3d
    inliers = split_by_pair(in2d, ctx.problem.offsets)
    n2d, n3d = int(np.count_nonzero(in2d)), int(np.count_nonzero(in3d))
    support = obs.pose_support(ctx.problem, R, t, in2d, ctx.gravity_world, ctx.query_gravity)
    spread = support.collinearity
    near_collinear = spread < PROFILE_BELOW_RATIO and n3d < options.min_inliers
    # Residuals within one reference are correlated (its pose error, calibration, model
    # errors): thousands of matches are not thousands of independent constraints.
    # With a measured map prior and 2D-3D support the map errors are modelled and nothing is
    # left to inflate (on the shared data and generated worlds the inflated std was 2-5x the
    # error). A pose on 2D-2D constraints alone keeps the inflation: cross-session matches
    # (fountain_p11 map, entry_p10 queries) gave a pose 0.98 m off with a 0.08 m std without it.
    modelled = options.map_prior_measured and n3d >= options.min_inliers
    correlation = 1.0 if modelled else obs.correlation_inflation(n2d + n3d, len(support.supporting))
    cov = _position_covariance(estimator, options, ref, support, correlation)
    finite = bool(np.isfinite(cov).all())
    std = math.sqrt(max(sym_eigvals(cov)[0], 0.0)) if finite else math.inf
    if math.isfinite(std) and near_collinear:
        # Near-collinear geometry: the linearised covariance is over-confident in the curved
        # valley of the cost; profile the cost along the weak directions, at 3σ (does the
        # quadratic model hold?) and at the decision scale.
        # With a map pose uncertainty the profile is of the map-prior objective: the reference
        # poses follow the probe within their prior, as map errors bend the valley (KITTI, 2D-2D
        # mode, 2p1p: a pose 1.38 m off had a std of 0.255 m profiled with the map held exact).
        # The 3σ probe profiles the refinement's own objective; the decision-scale probe, with a
        # map pose uncertainty, the map-prior objective.
        prior = options.map_rotation_std_deg > 0 or options.map_position_std_m > 0
        probes = [(min(max(3.0 * std, 0.02), 2.0), False), (min(options.max_position_std_m, 2.0), prior)]
        for u in obs.weak_directions(estimator, R, t, support.supporting, cov):
            for d, with_prior in probes:
                std = max(
                    std,
                    correlation
                    * obs.profile_std(
                        estimator,
                        R,
                        t,
                        in2d,
                        in3d,
                        ref.sigma,
                        None if with_prior else ref.cost,
                        u,
                        d,
                        map_prior=with_prior,
                    ),
                )
    rival = max((float(np.linalg.norm(other - (-R.T @ t))) for other in rivals), default=0.0)
    linear_std, std = std, max(std, rival)
    model = "planar" if support.fit.holds(options.planar_tolerance_deg) else "6dof"
    pose = Pose._unchecked(R, t)  # a refined rotation (exp map of a rotation): valid by construction
    return _Judging(
        ctx, cand, t0, support, correlation, cov, std, linear_std, rival, pose, model, inliers, n2d, n3d
    )


def _check_support(j: _Judging) -> PoseEstimate | None:
    """Enough inliers, from at least two map images, beyond what random matches would give."""
    options, problem, ref = j.ctx.options, j.ctx.problem, j.cand.ref
    n2d, n3d, supporting = j.n2d, j.n3d, j.support.supporting
    if n2d + n3d < options.min_inliers:
        return j.fail(
            Status.TOO_FEW_INLIERS,
            f"best pose has {n2d + n3d} inliers, fewer than min_inliers={options.min_inliers}",
            with_pose=False,
        )
    if len(supporting) < 2 and n3d < options.min_inliers:
        return j.fail(
            Status.SINGLE_REFERENCE,
            f"only {len(supporting)} reference image(s) support the pose with >= {obs.MIN_PAIR_INLIERS} "
            "inliers: the position along the baseline cannot be verified; retrieve more map images",
        )
    if n3d < options.min_inliers:
        # Without 2D-3D constraints the pose rests on its 2D-2D inliers alone: at least two map
        # images must support it beyond what random matches would give it.
        chance = chance_inliers(problem, ref.R, ref.t, options.threshold_px)
        real = beyond_chance(j.support.pair_inliers[supporting], chance[supporting])
        if int(real.sum()) < 2:
            detail = ", ".join(f"{int(j.support.pair_inliers[k])} vs {chance[k]:.1f}" for k in supporting)
            return j.fail(
                Status.TOO_FEW_INLIERS,
                f"{int(real.sum())} of the {len(supporting)} supporting map images have more inliers than "
                f"random matches would give this pose (inliers vs chance: {detail}): the matches do not "
                "see the same scene; retrieve other map images or add map images of this place",
            )
    return None


def _check_distant_plane(j: _Judging) -> PoseEstimate | None:
    """Pairs that one homography explains are no evidence of the position on their own."""
    options, problem, estimator, ref = j.ctx.options, j.ctx.problem, j.cand.estimator, j.cand.ref
    R, t, in2d, in3d, n3d, supporting = ref.R, ref.t, ref.in2d, ref.in3d, j.n3d, j.support.supporting
    any_plane = j.cand.any_plane_degenerate
    planar = distant_planar_pairs(
        problem, R, t, in2d, supporting, PLANAR_TRANSFER_SCALE * options.threshold_px, any_plane=any_plane
    )
    if not planar.any():
        return None
    # A distant plane: one homography explains a pair's matches and the map images stand
    # close together relative to it; rotation and translation are entangled far beyond what
    # the linearised covariance says. Such pairs are no evidence of the position on their
    # own: with fewer than two others and no 2D-3D constraints the pose is refused;
    # otherwise the pose without them, and its uncertainty, bound the std.
    if n3d < options.min_inliers and len(supporting) - int(planar.sum()) < 2:
        why = (
            (
                "(one homography explains their matches: a plane, or too little parallax), on which the "
                "8-point algorithm cannot tell the epipolar geometry; use method='auto'"
            )
            if any_plane
            else (
                "(one homography explains their matches, far beyond the map images' spread): rotation and "
                "translation cannot be told apart; add map images that see the scene from closer or from other "
                "directions"
            )
        )
        return j.fail(
            Status.DEGENERATE_STRUCTURE,
            f"{int(planar.sum())} of the {len(supporting)} supporting map "
            f"images see {'a plane' if any_plane else 'a distant plane'} {why}",
        )
    keep2d = in2d & ~np.isin(problem.pair, supporting[planar])
    prior = n3d > 0 and (options.map_rotation_std_deg > 0 or options.map_position_std_m > 0)
    R_w, t_w, H_w, sigma_w, cost_w = (estimator._refine_with_map_prior if prior else estimator._refine)(
        R, -R.T @ t, keep2d, in3d, 6
    )
    alone = RefinedPose(
        R_w, t_w, centre_covariance(H_w, sigma_w), sigma_w, cost_w, ref.score, keep2d, in3d, H=H_w
    )
    cov_w = _position_covariance(estimator, options, alone, j.support, j.correlation)
    std_w = math.sqrt(max(sym_eigvals(cov_w)[0], 0.0)) if np.isfinite(cov_w).all() else math.inf
    j.std = max(j.std, float(np.linalg.norm(-R_w.T @ t_w - (-R.T @ t))), std_w)
    return None


def _check_position(j: _Judging) -> PoseEstimate | None:
    """An observable position within ``max_position_std_m``, one the references agree on."""
    options, estimator, ref = j.ctx.options, j.cand.estimator, j.cand.ref
    spread, n3d = j.support.collinearity, j.n3d
    collinear = n3d < options.min_inliers and spread < options.min_collinearity_ratio
    if not collinear and j.rival > options.max_position_std_m and j.linear_std <= options.max_position_std_m:
        return j.fail(
            Status.AMBIGUOUS_POSE,
            f"another search's pose {j.rival:.3g} m away explains the matches nearly "
            f"as well (MSAC cost within {100 * (RIVAL_COST_RATIO - 1):.0f} %): the data do not single out "
            "one position; more matches or map images",
        )
    if collinear or not j.std <= options.max_position_std_m:
        hint = "" if options.structure == Structure.TRACKS else "; try structure='tracks'"
        why = (
            (
                f"the query and reference centres are nearly collinear (ratio {spread:.2g} < "
                f"min_collinearity_ratio = {options.min_collinearity_ratio})"
            )
            if collinear
            else (f"std {j.std:.3g} m > max_position_std_m = {options.max_position_std_m} m")
        )
        return j.fail(Status.DEGENERATE_SCALE, f"position unobservable from the inliers: {why}{hint}")
    if options.refine:
        R, t, in2d, in3d, supporting = ref.R, ref.t, ref.in2d, ref.in3d, j.support.supporting
        prior = n3d > 0 and (options.map_rotation_std_deg > 0 or options.map_position_std_m > 0)
        jk = (
            obs.reference_jackknife_with_prior(estimator, R, t, in2d, in3d, supporting)
            if prior
            else obs.reference_jackknife(estimator, R, t, in2d, in3d, support=supporting)
        )
        if math.isfinite(jk.position_std_m):
            j.std = max(j.std, jk.position_std_m)
            limit = min(options.max_reference_shift_std * j.std, options.max_position_std_m)
            if jk.max_shift_m > limit or jk.max_rotation_deg > 5.0:
                return j.fail(
                    Status.INCONSISTENT_REFERENCES,
                    f"leaving out reference {jk.worst_reference} moves the pose by {jk.max_shift_m:.3g} m / "
                    f"{jk.max_rotation_deg:.2g}° (limit {limit:.3g} m / 5°): the references disagree",
                )
    if not j.std <= options.max_position_std_m:
        return j.fail(
            Status.DEGENERATE_SCALE,
            f"position std {j.std:.3g} m > max_position_std_m = "
            f"{options.max_position_std_m} m after leave-one-reference-out verification",
        )
    return None


def _check_runner_ups(j: _Judging) -> PoseEstimate | None:
    """No other pose, a runner-up of the search or a restart of the refinement, far away
    explains the matches about as well."""
    options, cand = j.ctx.options, j.cand
    if cand.refine is not None and (len(cand.alternatives) or len(cand.pool[0])):
        # Few inliers per reference: a pose that absorbs a few outliers can explain the matches
        # as well as the truth, far beyond what the curvature at either optimum says
        # (benchmarks/robustness.py --protocol hard, 20 matches per pair: ~1 % of successes
        # were 0.2-3 m off with std 0.04-0.2 m before this check; about half are left).
        d = _rival_distance(
            cand.estimator,
            cand.ref,
            j.n2d + j.n3d,
            cand.alternatives,
            cand.pool,
            cand.refine,
            3.0 * j.std + 0.05,
        )
        if d > 0.0:
            j.std = max(j.std, d)
            if not j.std <= options.max_position_std_m:
                return j.fail(
                    Status.AMBIGUOUS_POSE,
                    f"another pose {d:.3g} m away explains the matches nearly as "
                    f"well (within {RIVAL_MARGIN_INLIERS} inliers' worth of MSAC cost): the data do not "
                    "single out one position; more matches or map images, or structure='tracks'",
                )
    if cand.refine is not None and j.n2d + j.n3d < PROFILE_BELOW_INLIERS:
        # Few constraints: other basins of the cost, with other inlier sets, may explain the
        # matches as well (Strecha entry_p10 against the fountain_p11 map: a pose 0.95 m off with
        # std 0.23 m, while restarts 0.7 m away found lower costs).
        d = _basin_distance(cand.estimator, cand.ref, cand.refine, 3.0 * j.std + 0.05)
        if d > 0.0:
            j.std = max(j.std, d)
            if not j.std <= options.max_position_std_m:
                return j.fail(
                    Status.AMBIGUOUS_POSE,
                    f"a restart of the refinement {d:.3g} m away converged to a pose "
                    f"that explains the matches as well (within {RESTART_MARGIN_INLIERS} inlier's worth of "
                    "MSAC cost, or better): the data do not single out one position; more matches or map "
                    "images",
                )
    return None
