"""What the matches can tell about a refined pose: observability, uncertainty, verification.

Estimation (:mod:`planarloc.robust.estimators`) finds a pose; this module judges it. Every
function takes the problem (or its estimator, for refinement) and a refined pose ``(R, t)``
(``cam_from_world``) and returns numbers, never a new estimate:

* :func:`pose_support` — which references support the pose, how collinear their centres are
  with the query's (the straight corridor / road degeneracy of 2D-2D constraints), the
  median distance to them, and the planar fit (tilt from the references' gravity,
  elevation of the query above or below their plane);
* :func:`weak_directions`, :func:`profile_std` — a secant profile of the cost along weakly
  observed directions of near-collinear geometry;
* :func:`map_covariance` — the map's pose uncertainty propagated into the query position;
* :func:`points_covariance` — the uncertainty of triangulated 2D-3D points (their keypoint noise
  and their map images' pose errors) propagated into it;
* :func:`correlation_inflation` — residuals correlated within one reference;
* :func:`~planarloc.robust.jackknife.reference_jackknife` (its own module) —
  leave-one-reference-out refinements: an empirical spread that sees what the linearised
  covariance cannot (one reference with a wrong pose, a wrong basin supported by one
  reference, model errors), and the disagreement between references.

The per-estimate numbers come from compiled kernels (:func:`support_kernel`,
:func:`~planarloc.robust.jackknife.jackknife_kernel`,
:func:`~planarloc.robust.refinement.map_centre_covariance`): they run
once per query on a few hundred inliers, where Python and numpy call overhead would cost more
than the arithmetic (issue 10: the whole verification is a fraction of PoseLib's RANSAC time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.numerics.cholesky import spd_inverse
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.refinement import (
    map_centre_covariance,
    map_uncertainty_covariance,
    residuals_jacobian,
)

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


def correlation_inflation(
    num_inliers: int, num_supporting: int, per_reference: int = EFFECTIVE_CONSTRAINTS_PER_REFERENCE
) -> float:
    """Factor (≥ 1) on standard deviations for residuals that are correlated per reference.

    The linearised covariance ``σ̂² (JᵀWJ)⁻¹`` treats every inlier as an independent
    measurement, so its standard deviations shrink like ``1/√N``. Residuals of one reference
    share that reference's pose error, calibration and the planar-model error, which do not
    average out; on real sequences (KITTI) the error of 2D-2D poses is 2–3× the linearised
    std with ~1,000 inliers. Counting at most ``per_reference`` independent constraints per
    supporting reference gives the factor ``sqrt(N / (per_reference · n_refs))``.

    Args:
        num_inliers: 2D-2D plus 2D-3D inliers N; num_supporting: supporting references.
    """
    return math.sqrt(max(1.0, num_inliers / (per_reference * max(num_supporting, 1))))


@njit(cache=True, error_model="numpy")
def support_kernel(
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    offsets: np.ndarray,
    ref_R: np.ndarray,
    ref_t: np.ndarray,
    gravity_world: np.ndarray,
    query_gravity: np.ndarray,
    min_pair_inliers: int,
) -> tuple[np.ndarray, float, float, float, float]:
    """The numbers of :class:`PoseSupport` in one compiled call; see :func:`pose_support`."""
    P = offsets.shape[0] - 1
    counts = np.zeros(P, dtype=np.int64)
    for p in range(P):
        for i in range(offsets[p], offsets[p + 1]):
            if in2d[i]:
                counts[p] += 1
    c = -m3.t_vec(R, t)
    centres = np.empty((P, 3))
    for p in range(P):
        cp = m3.t_vec(ref_R[p], ref_t[p])
        for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            centres[p, a] = -cp[a]
    # collinearity: s2 / s1 of the centred {query centre} ∪ {supporting reference centres}
    pts = [c]
    for p in range(P):
        if counts[p] >= min_pair_inliers:
            pts.append(centres[p])
    collinearity = 0.0
    if len(pts) >= 3:
        mean = np.zeros(3)
        for q in pts:
            mean += q / len(pts)
        S = np.zeros((3, 3))
        for q in pts:
            d = q - mean
            for a in range(3):
                for b in range(3):
                    S[a, b] += d[a] * d[b]
        l1, l2, _ = m3.sym_eigvals(S)
        collinearity = np.sqrt(max(l2, 0.0) / l1) if l1 > 0 else 0.0
    # median distance to the references with inliers (all of them when none has any)
    has = counts > 0
    dist = np.empty(P)
    k = 0
    for p in range(P):
        if has[p] or not has.any():
            dist[k] = np.sqrt(np.sum((centres[p] - c) ** 2))
            k += 1
    median_distance = np.median(dist[:k]) if k else np.nan
    # planar fit: tilt of the implied gravity, elevation over the supporting references
    g_pred = m3.vec(R, gravity_world)
    cos_t = np.sum(g_pred * query_gravity) / max(
        np.sqrt(np.sum(g_pred * g_pred) * np.sum(query_gravity**2)), 1e-300
    )
    tilt = np.degrees(np.arccos(min(1.0, max(-1.0, cos_t))))
    heights = np.empty(P)
    horizontal = np.empty(P)
    k = 0
    for p in range(P):
        if counts[p] >= min_pair_inliers:
            b = c - centres[p]
            h = np.sum(b * gravity_world)
            heights[k] = h
            horizontal[k] = np.sqrt(max(np.sum(b * b) - h * h, 0.0))
            k += 1
    elevation = 0.0
    if k:
        elevation = np.degrees(np.arctan2(abs(np.median(heights[:k])), max(np.median(horizontal[:k]), 1e-9)))
    return counts, collinearity, median_distance, tilt, elevation


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


@dataclass(frozen=True)
class PoseSupport:
    """Which references support a pose, and the geometry of their centres around it.

    Attributes:
        pair_inliers: (P,) 2D-2D inliers per pair.
        supporting: indices of the pairs with at least ``MIN_PAIR_INLIERS`` of them.
        collinearity: ``s₂ / s₁``, the ratio of the two largest singular values of the centred
            set of the query centre and the supporting reference centres: 0 for collinear
            centres (a straight corridor or road), O(1) for a spread configuration (fewer than
            3 points: 0). 2D-2D constraints fix the position by intersecting lines from the
            reference centres, so it is unobservable along the line when the ratio is small.
        median_distance_m: median distance from the query centre to the references with
            inliers (to all references when none has any).
        fit: :class:`PlanarFit` of the pose.
    """

    pair_inliers: np.ndarray
    supporting: np.ndarray
    collinearity: float
    median_distance_m: float
    fit: PlanarFit


def pose_support(
    problem,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    gravity_world: np.ndarray,
    query_gravity: np.ndarray,
    min_pair_inliers: int = MIN_PAIR_INLIERS,
) -> PoseSupport:
    """:class:`PoseSupport` of ``cam_from_world = (R, t)`` with 2D-2D inliers ``in2d`` (N,).

    Args:
        gravity_world: (3,) unit gravity (down) in the world frame (from the references).
        query_gravity: (3,) unit gravity assumed in the query camera frame.

    The planar fit's elevation is the median height offset over the median horizontal
    baseline: robust to one short baseline (collinear sequences), where a per-baseline angle
    would be dominated by centimetres of noise.
    """
    # Writable copies (np.array copies): numba compiles a kernel once per readonly flag of each
    # argument, and a readonly gravity or pose (a cached or broadcast array) made the first
    # query after `planarloc warmup` compile this kernel again (6 s on KITTI; cold_start.py).
    counts, col, dist, tilt, elev = support_kernel(
        np.array(R, dtype=float),
        np.array(t, dtype=float),
        in2d,
        problem.offsets,
        problem.ref_R,
        problem.ref_t,
        np.array(gravity_world, dtype=float),
        np.array(query_gravity, dtype=float),
        min_pair_inliers,
    )
    return PoseSupport(
        counts,
        np.flatnonzero(counts >= min_pair_inliers),
        float(col),
        float(dist),
        PlanarFit(float(tilt), float(elev)),
    )


def weak_directions(
    est, R: np.ndarray, t: np.ndarray, support: np.ndarray, cov: np.ndarray
) -> list[np.ndarray]:
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
    for k in support:
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


def profile_std(
    est,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    in3d: np.ndarray,
    sigma: float,
    cost: float | None,
    direction: np.ndarray,
    distance: float,
    map_prior: bool = False,
) -> float:
    """Secant estimate of the position std along ``direction`` (unit, world frame).

    The centre is moved by ``±distance`` along ``direction`` and held there while the
    rotation and the two other centre coordinates are re-optimised on the same inliers.
    If the robust cost rises by ``ΔC``, a quadratic profile ``ΔC/σ̂² = d²/(2 std²)``
    gives ``std = d / sqrt(2 ΔC / σ̂²)``; a flat profile (ΔC ≈ 0) gives inf. Unlike the
    linearised covariance, this sees curved, banana-shaped valleys of near-degenerate
    geometry (query almost collinear with the reference centres) and a second minimum
    nearby (a distant scene, where rotation and translation trade off).

    ``cost``: the robust cost at the optimum under the same objective, or None to evaluate it
    here (the profile's own refinement held at distance 0). ``map_prior``: profile the
    objective of :func:`planarloc.robust.map_prior.refine_with_map_prior` (the pose came from
    it), with the reference poses free under the map prior.
    """
    u = direction / np.linalg.norm(direction)
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    v1 = np.cross(u, a)
    v1 /= np.linalg.norm(v1)
    B = np.ascontiguousarray(np.stack([u, v1, np.cross(u, v1)], axis=1))
    fixed = np.array([False, False, False, True, False, False])
    c = -R.T @ t
    refine = est._refine_with_map_prior if map_prior else est._refine
    if cost is None:
        *_, cost = refine(R, c, in2d, in3d, 6, B, fixed)
    worst = 0.0
    for sgn in (1.0, -1.0):
        *_, c_moved = refine(R, c + sgn * distance * u, in2d, in3d, 6, B, fixed)
        rise = max(c_moved - cost, 0.0) / (sigma * sigma)
        worst = max(worst, distance / np.sqrt(2.0 * rise) if rise > 0 else np.inf)
    return worst


def map_covariance(
    est,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    in3d: np.ndarray,
    prior: tuple[float, float] | None = None,
) -> np.ndarray:
    """(3, 3) position covariance caused by the map's pose uncertainty: ``prior`` (rotation std
    in degrees, position std in metres), default the options' ``map_*_std``."""
    p, o = est.p, est.options
    rotation_deg, position_m = prior if prior is not None else (o.map_rotation_std_deg, o.map_position_std_m)
    return map_centre_covariance(
        *map_uncertainty_covariance(
            np.ascontiguousarray(R),
            np.ascontiguousarray(t),
            p.arrays,
            np.flatnonzero(in2d),
            np.flatnonzero(in3d),
            o.threshold_px,
            float(np.radians(rotation_deg)),
            float(position_m),
        )
    )


@njit(cache=True, error_model="numpy")
def points_centre_covariance(
    R: np.ndarray,
    t: np.ndarray,
    prob: ProblemArrays,
    X3d_cov: np.ndarray,
    X3d_views: np.ndarray,
    X3d_pose_jac: np.ndarray,
    idx3d: np.ndarray,
    H: np.ndarray,
    loss_scale: float,
    map_rotation_var: float,
    map_position_var: float,
) -> np.ndarray:
    """(3, 3) covariance of the query centre caused by the 2D-3D points' own uncertainty.

    The refinement solves ``Σ w Jᵀ r = 0``; a point moved by ``δX`` moves its residuals by
    ``J_X δX`` and the pose by ``δq = −H⁻¹ Σ w Jᵀ J_X δX``. For a reprojection residual
    ``J_X = −J_c`` (the point and the centre enter as ``X − c``). Two sources move the points:

    * the keypoint noise of their triangulation, independent per point:
      ``Σ_q = H⁻¹ (Σ_i w_i² J_iᵀ J_X,i Σ_X,i J_X,iᵀ J_i) H⁻¹``;
    * the pose errors of the map images they were triangulated from, ``δX_i = S_i δθ``
      (``X3d_pose_jac``, views ``X3d_views``), shared by every point of a map image, so they
      do not average out over points (a query nearly collinear with the map images of a road
      sees its points' depths, and so its position along the road, move with a 0.1° yaw of
      one of them): ``Σ_q = H⁻¹ (Σ_v B_v Λ B_vᵀ) H⁻¹`` with ``B_v = Σ_i w_i J_iᵀ J_X,i S_i,v``
      and ``Λ = diag(map_rotation_var I₃, map_position_var I₃)`` (rad², m²; the map prior's).
      The final refinement also estimates these poses from the 2D-2D matches under the same
      prior (its H is the marginal one, so ``σ̂² H⁻¹`` holds the prior's share of the same
      errors). The first-order cross terms between the two shares are left out: computed in
      full (``σ̂² H⁻¹ (B_v C_vᵀ + C_v B_vᵀ) H⁻¹`` with ``C_v = H_qv H_vv⁻¹``, the pair's blocks of
      the joint normal equations), they changed the std by under 0.5 % on KITTI and on the
      generated roads of ``tests/robust/test_structure_trust.py``.

    ``H`` is the refinement's normal matrix (the marginal one with the map prior, which leaves
    2D-3D rows alone). Inf-filled when H is singular.
    """
    m = 2 * idx3d.shape[0]
    r = np.empty(m)
    J = np.empty((m, 6))
    c = -m3.t_vec(R, t)
    residuals_jacobian(R, c, np.eye(3), prob, np.zeros(0, dtype=np.int64), idx3d, r, J, np.empty((0, 3)))
    s2 = loss_scale * loss_scale
    n_views = 0
    for n in range(idx3d.shape[0]):
        for slot in range(2):
            n_views = max(n_views, X3d_views[idx3d[n], slot] + 1)
    Bv = np.zeros((n_views, 6, 6))
    M = np.zeros((6, 6))
    for n in range(idx3d.shape[0]):
        S = X3d_cov[idx3d[n]]
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for u in range(2):
                    ru = 2 * n + u
                    wu = 1.0 / (1.0 + r[ru] * r[ru] / s2)
                    for v in range(2):
                        rv = 2 * n + v
                        wv = 1.0 / (1.0 + r[rv] * r[rv] / s2)
                        # (J_X Σ J_Xᵀ)[u, v] with J_X = −J_c
                        jsj = 0.0
                        for k in range(3):
                            for l2 in range(3):
                                jsj += J[ru, 3 + k] * S[k, l2] * J[rv, 3 + l2]
                        acc += wu * J[ru, a] * jsj * wv * J[rv, b]
                M[a, b] += acc
        for slot in range(2):
            view = X3d_views[idx3d[n], slot]
            if view < 0:
                continue
            Sv = X3d_pose_jac[idx3d[n], slot]
            for u in range(2):
                ru = 2 * n + u
                wu = 1.0 / (1.0 + r[ru] * r[ru] / s2)
                for k in range(6):
                    jxs = 0.0  # (J_X S_v)[u, k]
                    for l2 in range(3):
                        jxs -= J[ru, 3 + l2] * Sv[l2, k]
                    for a in range(6):
                        Bv[view, a, k] += wu * J[ru, a] * jxs
    for view in range(n_views):
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for k in range(6):
                    acc += Bv[view, a, k] * Bv[view, b, k] * (map_rotation_var if k < 3 else map_position_var)
                M[a, b] += acc
    Hi = np.empty((6, 6))
    if not spd_inverse(H, Hi, 0.0):
        return np.full((3, 3), np.inf)
    out = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            acc = 0.0
            for k in range(6):
                for l2 in range(6):
                    acc += Hi[3 + a, k] * M[k, l2] * Hi[l2, 3 + b]
            out[a, b] = acc
    return out


def points_covariance(est, R: np.ndarray, t: np.ndarray, in3d: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(3, 3) centre covariance from the 2D-3D points' covariance and their map images' pose
    uncertainty (``options.map_*_std``; :func:`points_centre_covariance`)."""
    p, o = est.p, est.options
    idx3d = np.flatnonzero(in3d)
    if len(idx3d) == 0 or not (np.any(p.X3d_cov[idx3d]) or np.any(p.X3d_views[idx3d] >= 0)):
        return np.zeros((3, 3))
    return points_centre_covariance(
        np.ascontiguousarray(R),
        np.ascontiguousarray(t),
        p.arrays,
        p.X3d_cov,
        p.X3d_views,
        p.X3d_pose_jac,
        idx3d,
        np.ascontiguousarray(H),
        o.threshold_px,
        math.radians(o.map_rotation_std_deg) ** 2,
        float(o.map_position_std_m) ** 2,
    )
