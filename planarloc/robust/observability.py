"""What the matches can tell about a refined pose: observability, uncertainty, verification.

Estimation (:mod:`planarloc.robust.estimators`) finds a pose; this module judges it. Every
function takes the problem's estimator (for its matches, inliers and refinement) and a
refined pose ``(R, t)`` (``cam_from_world``) and returns numbers, never a new estimate:

* :func:`centre_collinearity`, :func:`weak_directions`, :func:`profile_std` — the collinear
  (straight corridor / road) degeneracy of 2D-2D constraints and a secant profile of the
  cost along weakly observed directions;
* :func:`map_covariance`, :func:`median_reference_distance` — the map's pose uncertainty
  propagated into the query position;
* :func:`reference_jackknife` — leave-one-reference-out refinements: an empirical spread that
  sees what the linearised covariance cannot (one reference with a wrong pose, a wrong
  basin supported by one reference, model errors), and the disagreement between references;
* :func:`planar_fit` — how far a pose is from the planar model (tilt from the references'
  gravity, elevation of the query above or below their plane).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

import numpy as np

from planarloc.robust.refinement import map_covariance_from_parts, map_uncertainty_covariance

MIN_PAIR_INLIERS = 5  # a reference "supports" a pose with at least this many 2D-2D inliers
# Independent constraints one reference image is worth for the covariance (see correlation_inflation).
EFFECTIVE_CONSTRAINTS_PER_REFERENCE = 30


def reference_centres(problem) -> np.ndarray:
    """(P, 3) world centres of the references."""
    return -np.einsum("pji,pj->pi", problem.ref_R, problem.ref_t)


def supporting_pairs(problem, in2d: np.ndarray, min_inliers: int = MIN_PAIR_INLIERS) -> np.ndarray:
    """Indices of the pairs with at least ``min_inliers`` 2D-2D inliers."""
    if len(in2d) == 0:
        return np.zeros(0, dtype=np.int64)
    counts = np.add.reduceat(in2d.astype(np.int64), problem.offsets[:-1])
    counts[np.diff(problem.offsets) == 0] = 0
    return np.flatnonzero(counts >= min_inliers)


def correlation_inflation(problem, in2d: np.ndarray, num_inliers_3d: int,
                          per_reference: int = EFFECTIVE_CONSTRAINTS_PER_REFERENCE) -> float:
    """Factor (≥ 1) on standard deviations for residuals that are correlated per reference.

    The linearised covariance ``σ̂² (JᵀWJ)⁻¹`` treats every inlier as an independent
    measurement, so its standard deviations shrink like ``1/√N``. Residuals of one reference
    share that reference's pose error, calibration and the planar-model error, which do not
    average out; on real sequences (KITTI) the error of 2D-2D poses is 2–3× the linearised
    std with ~1,000 inliers. Counting at most ``per_reference`` independent constraints per
    supporting reference gives the factor ``sqrt(N / (per_reference · n_refs))``.
    """
    n_refs = max(len(supporting_pairs(problem, in2d)), 1)
    n = int(in2d.sum()) + int(num_inliers_3d)
    return float(np.sqrt(max(1.0, n / (per_reference * n_refs))))


def median_reference_distance(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray) -> float:
    """Median distance from the query centre to the centres of references with inliers."""
    p = est.p
    c = -R.T @ t
    centres = reference_centres(p)
    has = np.add.reduceat(in2d.astype(np.int64), p.offsets[:-1]) > 0 if len(in2d) else np.zeros(0, bool)
    d = np.linalg.norm(centres[has] - c, axis=1) if has.any() else np.linalg.norm(centres - c, axis=1)
    return float(np.median(d))


def centre_collinearity(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray) -> float:
    """How far the query and reference centres are from lying on one line (scale-free).

    The ratio ``s₂ / s₁`` of the two largest singular values of the centred set of the
    query centre and the centres of the references with at least 5 inliers: 0 for
    collinear centres (a straight corridor or road), O(1) for a spread configuration.
    2D-2D constraints fix the query position by intersecting the lines from the
    reference centres, so it is unobservable along the line when the ratio is small.
    """
    p = est.p
    pts = [-R.T @ t] + [-p.ref_R[k].T @ p.ref_t[k] for k in supporting_pairs(p, in2d)]
    if len(pts) < 3:
        return 0.0
    P = np.array(pts)
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return float(sv[1] / sv[0]) if sv[0] > 0 else 0.0


def weak_directions(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray, cov: np.ndarray) -> list[np.ndarray]:
    """Directions along which the position may be unobservable (world frame).

    The weakest axis of the bearing configuration (and the largest axis of the linearised
    covariance when it differs by more than ~10°): with the query centre ``c`` and the
    reference centres ``c_p`` of pairs with inliers, ``A = Σ_p (I - u_p u_pᵀ) / |c - c_p|²``
    with ``u_p`` the unit bearing; collinear centres make its smallest eigenvalue vanish.
    """
    dirs = []
    if np.all(np.isfinite(cov)):
        dirs.append(np.linalg.eigh(cov)[1][:, -1])
    p = est.p
    c = -R.T @ t
    A = np.zeros((3, 3))
    for k in supporting_pairs(p, in2d):
        d = c - (-p.ref_R[k].T @ p.ref_t[k])
        n2 = float(d @ d)
        if n2 < 1e-12:
            continue
        u = d / np.sqrt(n2)
        A += (np.eye(3) - np.outer(u, u)) / n2
    dirs.append(np.linalg.eigh(A)[1][:, 0])
    if len(dirs) == 2 and abs(dirs[0] @ dirs[1]) > 0.98:
        dirs.pop(0)
    return dirs


def profile_std(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray, in3d: np.ndarray, sigma: float,
                cost: float, direction: np.ndarray, distance: float) -> float:
    """Secant estimate of the position std along ``direction`` (unit, world frame).

    The centre is moved by ``±distance`` along ``direction`` and held there while the
    rotation and the two other centre coordinates are re-optimised on the same inliers.
    If the robust cost rises by ``ΔC``, a quadratic profile ``ΔC/σ̂² = d²/(2 std²)``
    gives ``std = d / sqrt(2 ΔC / σ̂²)``; a flat profile (ΔC ≈ 0) gives inf. Unlike the
    linearised covariance, this sees curved, banana-shaped valleys of near-degenerate
    geometry (query almost collinear with the reference centres).
    """
    u = direction / np.linalg.norm(direction)
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    v1 = np.cross(u, a)
    v1 /= np.linalg.norm(v1)
    B = np.ascontiguousarray(np.stack([u, v1, np.cross(u, v1)], axis=1))
    fixed = np.array([False, False, False, True, False, False])
    c = -R.T @ t
    worst = 0.0
    for sgn in (1.0, -1.0):
        *_, c_moved = est._refine(R, c + sgn * distance * u, in2d, in3d, 6, B, fixed)
        rise = max(c_moved - cost, 0.0) / (sigma * sigma)
        worst = max(worst, distance / np.sqrt(2.0 * rise) if rise > 0 else np.inf)
    return worst


def map_covariance(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray, in3d: np.ndarray) -> np.ndarray:
    """(3, 3) position covariance caused by the map's pose uncertainty (options.map_*_std)."""
    p, o = est.p, est.options
    H, M, var = map_uncertainty_covariance(
        np.ascontiguousarray(R), np.ascontiguousarray(t), p.xq, p.xr, p.pair, np.flatnonzero(in2d),
        p.f_query, p.f_ref, p.ref_R, p.ref_t, p.xq3d, p.X3d, np.flatnonzero(in3d), o.threshold_px,
        float(np.radians(o.map_rotation_std_deg)), float(o.map_position_std_m))
    return map_covariance_from_parts(H, M, var)


@dataclass(frozen=True)
class Jackknife:
    """Leave-one-reference-out refinements of a pose.

    Attributes:
        num_references: references that support the pose (≥ ``MIN_PAIR_INLIERS`` inliers).
        position_std_m: jackknife standard deviation of the centre along its worst axis,
            ``sqrt(λ_max((n-1)/n Σ (c_k - c̄)(c_k - c̄)ᵀ))``; nan with fewer than 3 references.
        max_shift_m: largest distance of a leave-one-out centre from the full estimate.
        max_rotation_deg: largest rotation between a leave-one-out estimate and the full one.
        worst_reference: the pair whose removal moves the pose most (-1 if none).
    """

    num_references: int
    position_std_m: float
    max_shift_m: float
    max_rotation_deg: float
    worst_reference: int


def reference_jackknife(est, R: np.ndarray, t: np.ndarray, in2d: np.ndarray, in3d: np.ndarray,
                        max_iterations: int = 2) -> Jackknife:
    """Refine the pose once per supporting reference with that reference's matches left out.

    2D-3D constraints (tracks, depth) stay in every refinement: they tie the query to world
    points, not to one reference. Each refinement starts at the full estimate, so a few
    Gauss-Newton steps reach the leave-one-out optimum (``max_iterations``). With fewer than 3 supporting references nothing is left
    to compare and the spread is nan.

    References:
        Efron & Stein (1981), the jackknife estimate of variance; used here per reference
        because map-pose errors and wrong matches are correlated within a reference.
    """
    p = est.p
    support = supporting_pairs(p, in2d)
    n = len(support)
    if n < 3:
        return Jackknife(n, float("nan"), float("nan"), float("nan"), -1)
    c = -R.T @ t
    centres = np.empty((n, 3))
    rots = np.empty(n)
    for i, k in enumerate(support):
        keep = in2d.copy()
        keep[p.offsets[k]:p.offsets[k + 1]] = False
        Rk, tk, *_ = est._refine(R, c, keep, in3d, max_iterations)
        centres[i] = -Rk.T @ tk
        rots[i] = np.degrees(np.arccos(np.clip((np.trace(Rk @ R.T) - 1.0) / 2.0, -1.0, 1.0)))
    d = centres - centres.mean(axis=0)
    cov = (n - 1) / n * d.T @ d
    shifts = np.linalg.norm(centres - c, axis=1)
    worst = int(np.argmax(shifts))
    return Jackknife(n, float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0))), float(shifts[worst]),
                     float(rots.max()), int(support[worst]))


@dataclass(frozen=True)
class PlanarFit:
    """How well a pose fits the planar model relative to its references.

    Attributes:
        tilt_deg: angle between the query gravity the pose implies (``R · g_world``) and the
            query gravity assumed for the planar hypotheses.
        elevation_deg: the query's median height offset from the supporting references over
            the median horizontal baseline length, as an angle (0 for a query at their height).
    """

    tilt_deg: float
    elevation_deg: float

    def holds(self, tolerance_deg: float) -> bool:
        return self.tilt_deg <= tolerance_deg and self.elevation_deg <= tolerance_deg


def planar_fit(problem, R: np.ndarray, t: np.ndarray, in2d: np.ndarray, gravity_world: np.ndarray,
               query_gravity: np.ndarray) -> PlanarFit:
    """:class:`PlanarFit` of ``cam_from_world = (R, t)``.

    Args:
        gravity_world: (3,) unit gravity (down) in the world frame (from the references).
        query_gravity: (3,) unit gravity assumed in the query camera frame.
    """
    # Scalar math (math module): this runs once per estimate, on 3-vectors, where numpy's
    # per-call overhead dominates.
    g_pred = R @ gravity_world
    cos_t = float(g_pred @ query_gravity) / max(math.sqrt(float(g_pred @ g_pred) * float(query_gravity @ query_gravity)),
                                             1e-300)
    tilt = math.degrees(math.acos(min(1.0, max(-1.0, cos_t))))
    support = supporting_pairs(problem, in2d)
    if len(support) == 0:
        return PlanarFit(tilt, 0.0)
    b = (-R.T @ t) - reference_centres(problem)[support]             # (S, 3) baselines
    heights = b @ gravity_world                                        # query above/below each reference
    horizontal = np.sqrt(np.maximum((b * b).sum(axis=1) - heights * heights, 0.0))
    # The query's height offset from the references' level plane over the typical baseline
    # length: robust to one short baseline (collinear sequences) where a per-baseline angle
    # would be dominated by centimetres of noise.
    elev = math.degrees(math.atan2(abs(statistics.median(heights.tolist())),
                                   max(statistics.median(horizontal.tolist()), 1e-9)))
    return PlanarFit(tilt, elev)
