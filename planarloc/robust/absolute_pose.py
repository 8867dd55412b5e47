"""The public entry point: robust absolute pose of a query from matches to posed references."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.estimators import Planar2p1pEstimator, RelativePairEstimator
from planarloc.robust.options import Method, RansacOptions, Structure, parse_method
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.problem import build_problem
from planarloc.robust.ransac import ransac
from planarloc.robust.result import PoseEstimate, RansacStatistics
from planarloc.robust.sampling import eligible_pairs
from planarloc.robust.structure import triangulate_tracks

logger = logging.getLogger(__name__)

PROFILE_BELOW_RATIO = 0.15  # centre collinearity ratio under which the cost profile is checked

MIN_SAMPLE = {Method.P2P1: (2, 1), Method.P2P2: (2, 2), Method.NISTER: (5, 5), Method.STEWENIUS: (5, 5),
              Method.EIGHT: (8, 8)}


def _split(mask: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [mask[offsets[p]:offsets[p + 1]].copy() for p in range(len(offsets) - 1)]


def estimate_absolute_pose(
    query_camera: Camera,
    pairs: Sequence[PairMatches],
    method: Method | str = "2p1p",
    options: RansacOptions | None = None,
    query_gravity: object | None = None,
) -> PoseEstimate:
    """Absolute pose of a query image from 2D-2D matches to reference images with known poses.

    Args:
        query_camera: intrinsics of the query.
        pairs: one :class:`PairMatches` per retrieved reference image (at least 2).
        method: ``"2p1p"`` (paper Sec. IV-C, default), ``"2p2p"`` (Sec. IV-B), or the
            baselines ``"5p5p-nister"``, ``"5p5p-stewenius"``, ``"8p8p"``.
        options: :class:`RansacOptions`; defaults are the paper's thresholds (2 px, 2°).
        query_gravity: (3,) gravity direction (down) in the query camera frame, e.g. from an
            IMU; None assumes the query is mounted like the references (the median of their
            ``ref_gravity``, or upright when they have none).

    Returns:
        :class:`PoseEstimate`. ``success`` is True only for a supported pose whose position
        is observable; otherwise ``pose`` is None and ``status`` says why.

    Raises:
        ValueError: invalid input (NaN/inf, mismatched lengths, fewer than two pairs,
            non-rotation poses, unknown method) — before any work is done.

    Example:
        >>> est = estimate_absolute_pose(cam, pairs, method="2p1p",
        ...                              options=RansacOptions(structure="tracks"))  # doctest: +SKIP
        >>> est.pose.center if est.success else est.status  # doctest: +SKIP
    """
    t_start = time.perf_counter()
    method = parse_method(method)
    options = RansacOptions() if options is None else options
    if not isinstance(options, RansacOptions):
        raise ValueError(f"options: expected RansacOptions, got {type(options).__name__}")
    problem = build_problem(query_camera, pairs)
    stats = RansacStatistics()
    if options.structure == Structure.TRACKS:
        t0 = time.perf_counter()
        xq3, X3 = triangulate_tracks(problem, options.threshold_px, options.track_min_angle_deg)
        problem = problem.with_points3d(xq3, X3, np.full(len(X3), -1))
        stats.add_time("structure", time.perf_counter() - t0)
    stats.add_time("setup", time.perf_counter() - t_start)
    empty = _split(np.zeros(len(problem.xq), dtype=bool), problem.offsets)

    def failure(status: str, message: str, **kw) -> PoseEstimate:
        stats.add_time("total", time.perf_counter() - t_start)
        return PoseEstimate(None, False, status, message, kw.pop("inliers", empty), iterations=stats.iterations,
                            stats=stats, **kw)

    m1, m2 = MIN_SAMPLE[method]
    has_3d = len(problem.X3d) > 0 and method in (Method.P2P1, Method.P2P2)
    counts = problem.counts
    if not (eligible_pairs(counts, m1, m2) or (has_3d and (counts >= m1).any())):
        return failure("too_few_matches",
                       f"{method.value} needs {m1} matches in one pair and {m2} in another; "
                       f"got {counts.tolist()} matches per pair")

    if method == Method.P2P1:
        estimator = Planar2p1pEstimator(problem, options)
    else:
        estimator = RelativePairEstimator(problem, options, method)
    rng = np.random.default_rng(options.seed)
    out = ransac(estimator, options, rng, stats)
    if out.R is None and stats.rejected_degenerate > 0 and stats.rejected_degenerate >= (
            stats.rejected_rcheck + stats.rejected_pdcheck + stats.rejected_consistency):
        return failure("degenerate_scale",
                       f"no hypothesis: {stats.rejected_degenerate} samples were degenerate (triangulation "
                       "singular: query collinear with the reference centres); try structure='tracks'")
    if out.R is None:
        return failure("no_consistent_hypothesis",
                       f"none of {stats.hypotheses} hypotheses passed the checks (Rcheck {stats.rejected_rcheck}, "
                       f"Pdcheck {stats.rejected_pdcheck}, consistency {stats.rejected_consistency}, "
                       f"degenerate {stats.rejected_degenerate})")

    t0 = time.perf_counter()
    R, t = out.R, out.t
    R, t, cov, sigma, cost, in2d, in3d = estimator.refine_full(R, t, max_iterations=6 if options.refine else 0)
    if options.refine:
        # Refine again on the inliers of the refined pose when they changed.
        new2d, new3d = estimator.inliers(R, t)
        if not (np.array_equal(new2d, in2d) and np.array_equal(new3d, in3d)):
            R, t, cov, sigma, cost, in2d, in3d = estimator.refine_full(R, t, max_iterations=6)
    stats.add_time("refinement", time.perf_counter() - t0)
    t0 = time.perf_counter()
    in2d, in3d = estimator.inliers(R, t)
    inliers = _split(in2d, problem.offsets)
    n2d, n3d = int(in2d.sum()), int(in3d.sum())
    spread = estimator.centre_collinearity(R, t, in2d)
    near_collinear = spread < PROFILE_BELOW_RATIO and n3d < options.min_inliers
    if np.all(np.isfinite(cov)) and (options.map_rotation_std_deg > 0 or options.map_position_std_m > 0):
        if near_collinear:
            # Weak geometry amplifies map errors: propagate them through the full model.
            cov = cov + estimator.map_covariance(R, t, in2d, in3d)
        else:
            # Spread geometry: map errors move the query like the references, no amplification.
            d = estimator.median_reference_distance(R, t, in2d)
            cov = cov + np.eye(3) * (options.map_position_std_m**2 + (d * np.radians(options.map_rotation_std_deg)) ** 2)
    std = float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0))) if np.all(np.isfinite(cov)) else float("inf")
    if np.isfinite(std) and near_collinear:
        # Near-collinear geometry: the linearised covariance is over-confident in the curved
        # valley of the cost; profile the cost along the weak directions.
        # Probe at 3σ (does the quadratic model hold?) and at the decision scale.
        probes = {min(max(3.0 * std, 0.02), 2.0), min(options.max_position_std_m, 2.0)}
        for u in estimator.weak_directions(R, t, in2d, cov):
            for d in probes:
                std = max(std, estimator.profile_std(R, t, in2d, in3d, sigma, cost, u, d))
    stats.add_time("degeneracy_check", time.perf_counter() - t0)
    pose = Pose(R, t)
    if n2d + n3d < options.min_inliers:
        return failure("too_few_inliers", f"best pose has {n2d + n3d} inliers, fewer than min_inliers="
                       f"{options.min_inliers}", inliers=inliers, num_inliers=n2d, num_inliers_3d=n3d,
                       position_std_m=std)
    collinear = n3d < options.min_inliers and spread < options.min_collinearity_ratio
    if collinear or not std <= options.max_position_std_m:
        hint = "" if options.structure == Structure.TRACKS else "; try structure='tracks'"
        why = (f"the query and reference centres are nearly collinear (ratio {spread:.2g} < "
               f"min_collinearity_ratio = {options.min_collinearity_ratio})") if collinear else (
               f"std {std:.3g} m > max_position_std_m = {options.max_position_std_m} m")
        return failure("degenerate_scale", f"position unobservable from the inliers: {why}{hint}",
                       inliers=inliers, num_inliers=n2d, num_inliers_3d=n3d, position_std_m=std,
                       unreliable_pose=pose)
    stats.add_time("total", time.perf_counter() - t_start)
    return PoseEstimate(pose, True, "success", f"{n2d} 2D-2D and {n3d} 2D-3D inliers, position std {std:.3g} m",
                        inliers, n2d, n3d, stats.iterations, std, None, stats)
