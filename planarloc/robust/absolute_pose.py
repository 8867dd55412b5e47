"""The public entry point: robust absolute pose of a query from matches to posed references.

Stages: gravity levelling (planar families run on upright bearings), one RANSAC search per
hypothesis family (``auto``: planar 2p1p and 6DoF 5-point), robust 6DoF refinement of each
search's best, the lowest-cost pose wins; then :func:`planarloc.robust.verification.judge_pose`
judges it (collinear degeneracy, covariance with map uncertainty, leave-one-reference-out
verification, planar fit; the numbers from :mod:`planarloc.robust.observability`) and only a
pose that passes is a ``success``. An explicit planar method is also checked against the 6DoF
search (``planar_model_violated``).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.gravity import mean_direction, upright_from_gravity
from planarloc.robust import observability as obs
from planarloc.robust.estimators import (
    Planar2p1pEstimator,
    ProblemEstimator,
    RectifiedHypotheses,
    RelativePairEstimator,
    rectify_problem,
)
from planarloc.robust.final_refinement import FinalRefiner, RefinedPose
from planarloc.robust.options import Method, RansacOptions, Structure, parse_method, reprojection_threshold_px
from planarloc.robust.pair_matches import PairMatches, unit_gravity
from planarloc.robust.problem import AbsolutePoseProblem, build_problem
from planarloc.robust.ransac import ransac
from planarloc.robust.result import PoseEstimate, RansacStatistics
from planarloc.robust.rivals import RIVAL_COST_RATIO, RIVAL_MARGIN_INLIERS, with_rival
from planarloc.robust.sampling import eligible_pairs
from planarloc.robust.search_confidence import (
    RIVAL_CHECK_ITERATIONS,
    SECOND_SEARCH_BELOW_INLIERS,
    missed_by_all,
    rival_check_samples,
)
from planarloc.robust.status import DATA_LIMITED, Status
from planarloc.robust.structure import triangulate_tracks
from planarloc.robust.verification import Candidate, EstimateContext, failed_estimate, judge_pose

logger = logging.getLogger(__name__)


MIN_SAMPLE = {
    Method.AUTO: (2, 1),
    Method.P2P1: (2, 1),
    Method.P2P2: (2, 2),
    Method.NISTER: (5, 5),
    Method.STEWENIUS: (5, 5),
    Method.EIGHT: (8, 8),
}
PLANAR = (Method.P2P1, Method.P2P2)
# Hypothesis families searched per method, in order.
FAMILIES = {
    Method.AUTO: (Method.P2P1, Method.NISTER),
    Method.P2P1: (Method.P2P1,),
    Method.P2P2: (Method.P2P2,),
    Method.NISTER: (Method.NISTER,),
    Method.STEWENIUS: (Method.STEWENIUS,),
    Method.EIGHT: (Method.EIGHT,),
}
E_Y = np.array([0.0, 1.0, 0.0])
E_Y.setflags(write=False)
# An explicit planar method fails when a 6DoF pose elsewhere has less than this share of its cost.
PLANAR_VIOLATION_RATIO = 0.8


@dataclass(frozen=True)
class _Gravity:
    """Gravity of one problem: per reference (camera frames), the world's, the query's.

    ``levelled``: every camera is already upright (no rectification needed)."""

    refs: np.ndarray | None  # (P, 3) unit, reference camera frames (None when all are upright)
    world: np.ndarray  # (3,) unit, world frame (mean over references)
    query: np.ndarray  # (3,) unit, query camera frame (given, or the references' mount)
    query_given: bool
    levelled: bool


def _is_upright(g: np.ndarray) -> bool:
    return bool(np.abs(g - E_Y).max() <= 1e-12)


def _gravity(
    pairs: Sequence[PairMatches], problem: AbsolutePoseProblem, query_gravity: object | None
) -> _Gravity:
    if query_gravity is None and all(p.ref_gravity is None for p in pairs):  # the paper's case: all upright
        # World gravity = mean of R_kᵀ e_y = the references' second rows (unit already).
        s = problem.ref_R[:, 1, :].sum(axis=0)
        return _Gravity(None, s / math.sqrt(float(s @ s)), E_Y, False, True)  # refs unused when levelled
    given = [p.ref_gravity for p in pairs if p.ref_gravity is not None]
    g_refs = np.array([E_Y if p.ref_gravity is None else p.ref_gravity for p in pairs], dtype=float)
    g_world = mean_direction(np.einsum("pji,pj->pi", problem.ref_R, g_refs))
    g_query = (
        mean_direction(g_refs) if query_gravity is None else unit_gravity("query_gravity", query_gravity)
    )
    levelled = all(_is_upright(g) for g in given) and _is_upright(g_query)
    return _Gravity(g_refs, g_world, g_query, query_gravity is not None, levelled)


def _estimator(problem: AbsolutePoseProblem, options: RansacOptions, family: Method, gravity: _Gravity):
    """The estimator of one hypothesis family; planar families run on levelled bearings."""
    if family not in PLANAR:
        return RelativePairEstimator(problem, options, family)
    make = (
        Planar2p1pEstimator
        if family == Method.P2P1
        else (lambda prob, opt: RelativePairEstimator(prob, opt, Method.P2P2))
    )
    scorer = make(problem, options)
    if gravity.levelled or gravity.refs is None:  # refs is None only when levelled
        return scorer  # upright cameras: nothing to rectify
    Uq = upright_from_gravity(gravity.query)
    upright = make(rectify_problem(problem, Uq, upright_from_gravity(gravity.refs)), options)
    return RectifiedHypotheses(upright, scorer, Uq)


def _cross_check_families(
    method: Method, options: RansacOptions, problem: AbsolutePoseProblem
) -> list[Method]:
    """The searches that check a method chosen by name (``options.cross_check``): the other motion
    model's, and for a 6DoF baseline a second run of its own search (its own random samples).

    A 6DoF 2D-2D search has no planar model to fall back on when the query is tilted (another
    capture of the site), and on repeated facade windows the search can settle in one of
    several basins tens of metres apart whose costs differ by a few inliers (Strecha entry_p10
    against the fountain_p11 map); a second run that lands elsewhere is a rival answer."""
    if not options.cross_check or method == Method.AUTO:
        return []
    others = [Method.NISTER] if method in PLANAR else [Method.P2P1, method]
    return [f for f in others if _eligible(problem, f)]


def _eligible(problem: AbsolutePoseProblem, family: Method) -> bool:
    m1, m2 = MIN_SAMPLE[family]
    counts = problem.counts.tolist()
    if family not in PLANAR and len(problem.X3d) >= 3:
        return True  # P3P samples
    has_3d = len(problem.X3d) > 0 and family in PLANAR
    return eligible_pairs(counts, m1, m2) or (has_3d and max(counts, default=0) >= m1)


def estimate_absolute_pose(
    query_camera: Camera,
    pairs: Sequence[PairMatches],
    method: Method | str = "auto",
    options: RansacOptions | None = None,
    query_gravity: object | None = None,
) -> PoseEstimate:
    """Absolute pose of a query image from 2D-2D matches to reference images with known poses.

    Args:
        query_camera: intrinsics of the query.
        pairs: one :class:`PairMatches` per retrieved reference image (at least 2).
        method: ``"auto"`` (default: planar 2p1p on gravity-levelled bearings plus 6DoF
            5-point hypotheses, the lower-cost refined pose wins), ``"2p1p"`` (paper Sec.
            IV-C), ``"2p2p"`` (Sec. IV-B), or the baselines ``"5p5p-nister"``,
            ``"5p5p-stewenius"``, ``"8p8p"``.
        options: :class:`RansacOptions`; defaults are the paper's thresholds (2 px, 2°).
        query_gravity: (3,) gravity direction (down) in the query camera frame, e.g. from an
            IMU; None assumes the query is mounted like the references (the mean of their
            ``ref_gravity``, or upright when they have none).

    Returns:
        :class:`PoseEstimate`. ``success`` is True only for a supported pose whose position
        is observable and that survives leaving out any one reference; otherwise ``pose``
        is None and ``status`` says why.

    Raises:
        ValueError: invalid input (NaN/inf, mismatched lengths, fewer than two pairs,
            non-rotation poses, unknown method, zero gravity) — before any work is done.

    Example:
        >>> est = estimate_absolute_pose(
        ...     cam, pairs, options=RansacOptions(structure="tracks")
        ... )  # doctest: +SKIP
        >>> est.pose.center if est.success else est.status  # doctest: +SKIP
    """
    t_start = time.perf_counter()
    method = parse_method(method)
    options = RansacOptions() if options is None else options
    if not isinstance(options, RansacOptions):
        raise ValueError(f"options: expected RansacOptions, got {type(options).__name__}")
    stats = RansacStatistics()
    problem, gravity = _prepare(query_camera, pairs, options, query_gravity, stats)
    stats.add_time("setup", time.perf_counter() - t_start)
    run = _Estimation(
        EstimateContext(problem, options, gravity.world, gravity.query, stats, t_start),
        gravity,
        method,
        np.random.default_rng(options.seed),
    )
    families = [f for f in FAMILIES[method] if _eligible(problem, f)]
    if not families:
        m1, m2 = MIN_SAMPLE[method]
        return run.failure(
            Status.TOO_FEW_MATCHES,
            f"{method.value} needs {m1} matches in one map image and {m2} in another, or 2D-3D "
            f"constraints; got {problem.counts.tolist()} matches per map image and {len(problem.X3d)} "
            "2D-3D constraints: retrieve more map images or check the intrinsics",
        )
    est = run.estimate(families)
    # The whole call: a judged pose may still be checked (the short 6DoF search, a supported
    # alternative) after its judgement wrote its own elapsed time.
    stats.time_s["total"] = time.perf_counter() - t_start
    return est


@dataclass
class _Estimation:
    """One call of :func:`estimate_absolute_pose` past its setup: the searches, in the order
    that draws the same random samples, and the judgement of their poses."""

    ctx: EstimateContext
    gravity: _Gravity
    method: Method
    rng: np.random.Generator

    def failure(self, status: Status, message: str) -> PoseEstimate:
        ctx = self.ctx
        return failed_estimate(ctx.problem, ctx.stats, ctx.t_start, status, message)

    def search(self, family: Method, counted: bool, iterations: int | None = None) -> _Search | None:
        """One family's search; ``iterations``: a short check, refined with a quick look only."""
        ctx = self.ctx
        budget = ctx.options if iterations is None else ctx.options.with_iterations(iterations)
        return _search(
            ctx.problem,
            budget,
            family,
            self.gravity,
            self.rng,
            ctx.stats,
            counted,
            quick=iterations is not None,
        )

    def judge(self, best: _Search, searches: Sequence[_Search]) -> PoseEstimate:
        candidate = Candidate(
            best.scorer,
            best.refined,
            best.alternatives,
            best.pool,
            FinalRefiner(best.scorer, self.ctx.options),
            any_plane_degenerate=best.family == Method.EIGHT,
            # Every search could have found a pose of more support: all of them missed it.
            missed=missed_by_all(
                functools.partial(s.missed, best.refined.in2d, best.refined.in3d)
                for s in [best, *(s for s in searches if s is not best)]
            ),
        )
        return judge_pose(self.ctx, candidate, _rivals(best, searches))

    def or_supported(
        self, est: PoseEstimate, best: _Search, searches: list[_Search], checks: list[_Search]
    ) -> tuple[PoseEstimate, _Search]:
        """``est`` of ``best``, or, where it failed for want of data, the estimate of the pose the
        2D-3D constraints support (:func:`_better_supported`; with a search on them alone when no
        full search kept them) if that one passes. ``checks``: quick searches, rivals only."""
        if est.success or est.status not in DATA_LIMITED:
            return est, best
        ctx = self.ctx
        candidates = list(searches)
        if np.count_nonzero(best.refined.in3d) < ctx.options.min_inliers <= len(ctx.problem.X3d):
            candidates += [
                r
                for r in [_points_search(ctx.problem, ctx.options, self.gravity, self.rng, ctx.stats)]
                if r is not None
            ]
        supported = _better_supported(best, candidates)
        if supported is None:
            return est, best
        alternative = self.judge(supported, candidates + checks)
        return (alternative, supported) if alternative.success else (est, best)

    def estimate(self, families: list[Method]) -> PoseEstimate:
        """The planar model first. Where its refined pose fits the plane and either passes every
        check or fails one that says the data are weak (an unobservable position, disagreeing
        map images, a rival answer), a short 6DoF search (:func:`rival_check_samples` per map
        image, a quick refinement) only checks it: a pose of clearly lower cost means the planar
        search failed (a generated office tilted 1°: a planar pose 6.6° off on 993 inliers, the
        6DoF one right on 1,184 at a seventh of the cost), one elsewhere of about the same cost is
        a rival; at 60 % outliers the short search rarely finds anything, and costs little. A
        planar pose on few inliers is searched for twice first (:meth:`_second_search`). The
        full 6DoF search runs when the planar answer is in doubt: no pose, too few inliers, a
        pose that leaves the plane (a tilted query, one off the map's plane), or a clearly
        better 6DoF pose."""
        method, options, problem = self.method, self.ctx.options, self.ctx.problem
        found, others = [], []
        first = [f for f in families if f in PLANAR] if method in (Method.AUTO, *PLANAR) else families
        for family in first:
            found += [r for r in [self.search(family, counted=True)] if r is not None]
        if found and method in (Method.AUTO, *PLANAR) and (method == Method.AUTO or options.cross_check):
            found += self._second_search(min(found, key=lambda s: s.refined.score))
            best = min(found, key=lambda s: s.refined.score)
            est = self.judge(best, found)
            if est.model == "planar" and (est.success or est.status in DATA_LIMITED):
                checked = self._checked_planar(est, best, found)
                if isinstance(checked, PoseEstimate):
                    return checked
                others.append(checked)
        elif (
            found and method in PLANAR
        ):  # the paper's methods without the cross-check: the planar answer alone
            best = min(found, key=lambda s: s.refined.score)
            return self.judge(best, found)
        for family in families:
            if family not in first:
                found += [r for r in [self.search(family, counted=True)] if r is not None]
        others += [
            r
            for r in (self.search(f, counted=False) for f in _cross_check_families(method, options, problem))
            if r is not None
        ]
        if not found:
            return self.failure(*_no_hypothesis(self.ctx.stats, method, options))
        best = min(found, key=lambda s: s.refined.score)
        est, best = self.or_supported(self.judge(best, found + others), best, found, others)
        if method in PLANAR:
            return _planar_model_check(est, method, options, problem, best, others)
        return est

    def _second_search(self, best: _Search) -> list[_Search]:
        """Another search of ``best``'s family when its pose rests on fewer than
        ``SECOND_SEARCH_BELOW_INLIERS`` inliers (2D-2D and 2D-3D), else nothing: on so little
        support one search's basin is not evidence enough (:mod:`~planarloc.robust.search_confidence`)."""
        support = np.count_nonzero(best.refined.in2d) + np.count_nonzero(best.refined.in3d)
        if support >= SECOND_SEARCH_BELOW_INLIERS:
            return []
        return [r for r in [self.search(best.family, counted=True)] if r is not None]

    def _checked_planar(
        self, est: PoseEstimate, best: _Search, found: list[_Search]
    ) -> PoseEstimate | _Search:
        """The planar estimate checked by a short 6DoF search: the estimate when the check finds
        no clearly better pose, else the check's search (the full 6DoF search then runs)."""
        problem = self.ctx.problem
        samples = rival_check_samples(np.array([np.count_nonzero(m) for m in est.inliers]), problem.counts)
        check = None
        if _eligible(problem, Method.NISTER):
            check = self.search(Method.NISTER, counted=False, iterations=samples)
            if check is None and samples < RIVAL_CHECK_ITERATIONS:
                # No 6DoF hypothesis at all is no evidence for the planar pose: look again, at the
                # full budget (the demo's office query 1.6 s, seed 0: 2 samples gave nothing, and a
                # planar pose 0.28 m / 6.4° off at 7x the 6DoF pose's cost kept a 0.067 m std).
                check = self.search(Method.NISTER, counted=False, iterations=RIVAL_CHECK_ITERATIONS)
        margin = RIVAL_MARGIN_INLIERS * best.scorer.threshold_sq
        if check is None or check.refined.score >= best.refined.score - margin:
            self.ctx.stats.searches_skipped += 1
            est, best = self.or_supported(est, best, found, [] if check is None else [check])
            rivals = [] if not est.success or check is None else _rivals(best, [best, check])
            return with_rival(est, rivals[0], self.ctx.options) if rivals else est
        return check


@dataclass(frozen=True)
class _Search:
    """One hypothesis family's result: its refined best pose, and what a verifier may inspect.

    ``alternatives``: the other locally optimised models ``(R, t, MSAC cost)``; ``pool``: raw
    hypotheses near the best cost ``(R (k, 3, 3), t (k, 3))``; ``scorer``: the estimator that
    scores and refines on the original (not levelled) problem; ``missed(in2d, in3d)``: the
    chance that its samples missed a pose with these inliers or more
    (:mod:`planarloc.robust.search_confidence`)."""

    family: Method
    refined: RefinedPose
    alternatives: list
    pool: tuple[np.ndarray, np.ndarray]
    scorer: ProblemEstimator
    missed: Callable[[np.ndarray, np.ndarray], float]


def _prepare(
    query_camera: Camera,
    pairs: Sequence[PairMatches],
    options: RansacOptions,
    query_gravity: object | None,
    stats: RansacStatistics,
) -> tuple[AbsolutePoseProblem, _Gravity]:
    """Validated, flattened problem with its tracks (structure mode) and 2D-3D error scale."""
    problem = build_problem(query_camera, pairs)
    gravity = _gravity(pairs, problem, query_gravity)
    if options.structure == Structure.TRACKS:
        t0 = time.perf_counter()
        xq3, X3, C3, V3, J3 = triangulate_tracks(problem, options.threshold_px, options.track_min_angle_deg)
        problem = problem.with_points3d(xq3, X3, np.full(len(X3), -1), C3, V3, J3)
        stats.add_time("structure", time.perf_counter() - t0)
    return problem.with_reprojection_threshold(
        options.threshold_px / reprojection_threshold_px(options)
    ), gravity


def _search(
    problem: AbsolutePoseProblem,
    options: RansacOptions,
    family: Method,
    gravity: _Gravity,
    rng: np.random.Generator,
    stats: RansacStatistics,
    counted: bool,
    quick: bool = False,
) -> _Search | None:
    """RANSAC of one family (its own full iteration budget), then the final refinement of its best.

    ``counted``: its counters join the estimate's statistics (False for the cross-check of a
    method chosen by name, whose time alone is recorded); ``quick``: refine the best with one
    round of two iterations (a check that compares costs, not an answer)."""
    estimator = _estimator(problem, options, family, gravity)
    scorer = getattr(estimator, "scorer", estimator)
    search = RansacStatistics()
    out = ransac(estimator, options, rng, search)
    if counted:
        stats.merge(search)
    else:
        stats.add_time("cross_check", sum(search.time_s.values()))
    if out.R is None or out.t is None:  # both or neither
        return None
    t0 = time.perf_counter()
    refined = FinalRefiner(scorer, options)(out.R, out.t, quick)
    stats.add_time("refinement", time.perf_counter() - t0)
    missed = functools.partial(estimator.missed, samples=search.iterations)
    alternatives = list(zip(out.alt_R, out.alt_t, out.alt_cost))
    return _Search(family, refined, alternatives, (out.pool_R, out.pool_t), scorer, missed)


def _no_hypothesis(stats: RansacStatistics, method: Method, options: RansacOptions) -> tuple[Status, str]:
    """Status and message when no search produced a pose."""
    if stats.rejected_degenerate > 0 and stats.rejected_degenerate >= (
        stats.rejected_rcheck + stats.rejected_pdcheck + stats.rejected_consistency
    ):
        hint = "" if options.structure == Structure.TRACKS else "; try structure='tracks'"
        return Status.DEGENERATE_SCALE, (
            f"no hypothesis: {stats.rejected_degenerate} samples were degenerate "
            "(triangulation singular: query collinear with the map images)" + hint
        )
    return Status.NO_CONSISTENT_HYPOTHESIS, (
        f"none of the {stats.hypotheses} {method.value} hypotheses passed the checks (Rcheck "
        f"{stats.rejected_rcheck}, Pdcheck {stats.rejected_pdcheck}, consistency "
        f"{stats.rejected_consistency}, degenerate {stats.rejected_degenerate}): check the intrinsics and "
        "that the retrieved map images show the query's scene"
    )


def _rivals(best: _Search, searches: Sequence[_Search]) -> list[np.ndarray]:
    """Centres of other searches' refined poses that explain the matches almost as well.

    Where they lie elsewhere, the data do not single out one position (a flat or multi-modal
    cost), and the distance between the answers is a lower bound of the position's uncertainty.
    "Almost as well" holds for each kind of constraint: within ``RIVAL_COST_RATIO`` of the best
    MSAC cost, and with a 2D-3D share within that ratio (plus a couple of inliers' worth) of the
    best's: a pose that keeps the 2D-2D matches of a road but loses hundreds of 2D-3D
    constraints is no rival (2D-2D constraints barely see the position along the road)."""
    return [
        -s.refined.R.T @ s.refined.t
        for s in searches
        if s is not best
        and s.refined.score <= RIVAL_COST_RATIO * best.refined.score
        and _keeps_points(s, best)
    ]


def _keeps_points(a: _Search, b: _Search) -> bool:
    """Whether ``a``'s pose keeps about the 2D-3D constraints ``b``'s does: a 2D-3D cost within
    ``RIVAL_COST_RATIO`` of ``b``'s plus ``RIVAL_MARGIN_INLIERS`` inliers' worth. The one test
    of the 2D-3D share for rivals (:func:`_rivals`) and, reversed, for the pose the points
    support (:func:`_better_supported`)."""
    margin = RIVAL_MARGIN_INLIERS * b.scorer.threshold_sq
    return a.refined.score3d <= RIVAL_COST_RATIO * b.refined.score3d + margin


def _points_search(
    problem: AbsolutePoseProblem,
    options: RansacOptions,
    gravity: _Gravity,
    rng: np.random.Generator,
    stats: RansacStatistics,
) -> _Search | None:
    """A 6DoF search (P3P samples) scored by the 2D-3D constraints alone, its best refined on every
    constraint: the pose the points support when 2D-2D matches that cannot fix the position (a
    road, a corridor) outvote them in every other search."""
    points = _search(
        problem.points_only(), options, Method.NISTER, gravity, rng, stats, counted=False, quick=True
    )
    if points is None:
        return None
    scorer = _estimator(problem, options, Method.NISTER, gravity)
    t0 = time.perf_counter()
    refined = FinalRefiner(scorer, options)(points.refined.R, points.refined.t)
    stats.add_time("cross_check", time.perf_counter() - t0)
    return _Search(Method.NISTER, refined, [], (np.zeros((0, 3, 3)), np.zeros((0, 3))), scorer, points.missed)


def _better_supported(best: _Search, found: Sequence[_Search]) -> _Search | None:
    """The lowest-cost other search whose pose the 2D-3D constraints support where ``best``'s
    loses them, or None.

    ``best`` won on MSAC cost, but when its pose cannot be verified for want of data (it rests on
    2D-2D constraints that do not fix the position), the cost that made it win is no evidence
    either: along a road 2D-2D constraints barely see the position, and a 6DoF search there can
    slide a pose far along the road, where the epipolar lines of forward motion let in more wrong
    matches than the 2D-3D constraints it drops (``kitti_seq1`` frame 000002 on a compact map: a
    pose 146 m behind the map, 1,650 2D-2D and 0 of 323 2D-3D inliers, beat the planar pose with
    1,432 and 215 on cost). A search whose 2D-3D share of the cost is so much lower that
    ``best`` would not count as its rival (:func:`_rivals`) is judged in its place."""
    better = [s for s in found if s is not best and not _keeps_points(best, s)]
    return min(better, key=lambda s: s.refined.score) if better else None


def _planar_model_check(
    est: PoseEstimate,
    method: Method,
    options: RansacOptions,
    problem: AbsolutePoseProblem,
    best: _Search,
    checks: Sequence[_Search],
) -> PoseEstimate:
    """An explicit planar method's estimate, or ``planar_model_violated`` where its model fails:
    the more useful reason, also when the pose failed another check (a rival 6DoF pose can make
    it look ambiguous when the real trouble is the model)."""
    pose = est.pose if est.success else est.unreliable_pose
    if not options.cross_check or pose is None:
        return est
    if est.model != "planar":
        why = (
            f"the {method.value} pose does not fit the planar model it assumes (it implies a tilt or an "
            f"elevation above {options.planar_tolerance_deg}° relative to the map images)"
        )
    else:
        # A 6DoF pose elsewhere that explains the matches clearly better: the planar model failed.
        # "Clearly": by a share of the cost and by a few inliers' worth (noise-free data cost ~0).
        margin = RIVAL_MARGIN_INLIERS * best.scorer.threshold_sq
        better = [
            c
            for c in checks
            if c.refined.score < PLANAR_VIOLATION_RATIO * best.refined.score - margin
            and _different(problem, (pose.R, pose.t), (c.refined.R, c.refined.t))
        ]
        if not better:
            return est
        why = (
            f"a 6DoF pose explains the matches better than the {method.value} pose (MSAC cost "
            f"{better[0].refined.score:.4g} < {best.refined.score:.4g}) and lies elsewhere: the query is "
            "tilted or off the map's plane"
        )
    return PoseEstimate(
        None,
        False,
        Status.PLANAR_MODEL_VIOLATED,
        why + "; use method='auto'",
        est.inliers,
        est.num_inliers,
        est.num_inliers_3d,
        est.iterations,
        est.position_std_m,
        pose,
        est.stats,
        model="6dof",
    )


def _different(problem: AbsolutePoseProblem, a: tuple, b: tuple) -> bool:
    """Two poses are different answers when their centres differ by more than 5 % of the
    distance to the nearest reference centre or their rotations by more than 2°."""
    ca, cb = -a[0].T @ a[1], -b[0].T @ b[1]
    scale = np.linalg.norm(obs.reference_centres(problem) - ca, axis=1).min()
    angle = np.degrees(np.arccos(np.clip((np.trace(a[0] @ b[0].T) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(np.linalg.norm(ca - cb) > 0.05 * scale or angle > 2.0)
