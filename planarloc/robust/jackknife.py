"""Leave-one-reference-out refinements of a pose: an empirical spread that sees what the
linearised covariance cannot (one reference with a wrong pose, a wrong basin supported by one
reference, model errors), and the disagreement between references.

:func:`reference_jackknife` refines once per supporting reference in one compiled call
(:func:`jackknife_kernel`); :func:`reference_jackknife_with_prior` does the same for a pose
refined under the map prior (:mod:`planarloc.robust.map_prior`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.so3 import exp_so3
from planarloc.numerics.cholesky import solve_spd
from planarloc.robust.map_prior import refine_with_map_prior
from planarloc.robust.observability import supporting_pairs
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.refinement import (
    RefineSettings,
    StartPose,
    refine_pose_core,
    residuals_jacobian,
    with_iterations,
)


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


@njit(cache=True, error_model="numpy")
def _pair_normal_equations(
    R: np.ndarray, c: np.ndarray, prob: ProblemArrays, all2d: np.ndarray, idx3d: np.ndarray, loss_scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's share of the refinement's normal equations at ``(R, c)``: ``H`` (P + 1, 6, 6)
    and ``g`` (P + 1, 6) of the Cauchy-weighted rows of the 2D-2D inliers ``all2d`` of each pair,
    row P the 2D-3D inliers ``idx3d`` (kept in every leave-one-out problem)."""
    m = all2d.shape[0] + 2 * idx3d.shape[0]
    r = np.empty(m)
    J = np.empty((m, 6))
    residuals_jacobian(R, c, np.eye(3), prob, all2d, idx3d, r, J, np.empty((0, 3)))
    P = prob.offsets.shape[0] - 1
    Hp = np.zeros((P + 1, 6, 6))
    gp = np.zeros((P + 1, 6))
    s2 = loss_scale * loss_scale
    for row in range(m):
        q = prob.pair[all2d[row]] if row < all2d.shape[0] else P
        w = 1.0 / (1.0 + r[row] * r[row] / s2)
        for a in range(6):
            wa = w * J[row, a]
            gp[q, a] += wa * r[row]
            for b in range(6):
                Hp[q, a, b] += wa * J[row, b]
    return Hp, gp


@njit(cache=True, error_model="numpy")
def _first_step(
    R: np.ndarray, c: np.ndarray, A: np.ndarray, rhs: np.ndarray, max_iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """The pose after the first damped Gauss-Newton step ``A δ = rhs`` (``A`` is damped in
    place); ``(R, c)`` unchanged when no iteration is allowed or ``A`` is singular."""
    for a in range(6):
        A[a, a] += 1e-4 * max(A[a, a], 1e-12)  # the refinement's initial LM damping
    step = np.zeros(6)
    if max_iterations >= 1 and solve_spd(A, rhs, step):
        return m3.mul(exp_so3(step[:3]), R), c + step[3:]
    return R, c


@njit(cache=True, error_model="numpy")
def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle between two rotations, degrees."""
    tr = 0.0
    for a in range(3):
        for b in range(3):
            tr += Ra[a, b] * Rb[a, b]
    return np.degrees(np.arccos(min(1.0, max(-1.0, (tr - 1.0) / 2.0))))


@njit(cache=True, error_model="numpy")
def _centre_spread(centres: np.ndarray, mean: np.ndarray, c: np.ndarray) -> tuple[float, float, int]:
    """Of the leave-one-out ``centres`` (n, 3) with mean ``mean`` around the full estimate's
    centre ``c``: the jackknife std along the worst axis, the largest distance from ``c`` and
    the row at that distance."""
    n = centres.shape[0]
    cov = np.zeros((3, 3))
    worst, max_shift = 0, -1.0
    for i in range(n):
        shift = 0.0
        for a in range(3):
            shift += (centres[i, a] - c[a]) ** 2
            for b in range(3):
                cov[a, b] += (n - 1.0) / n * (centres[i, a] - mean[a]) * (centres[i, b] - mean[b])
        if shift > max_shift:
            worst, max_shift = i, shift
    lam, _, _ = m3.sym_eigvals(cov)
    return np.sqrt(max(lam, 0.0)), np.sqrt(max(max_shift, 0.0)), worst


@njit(cache=True, error_model="numpy")
def jackknife_kernel(
    R: np.ndarray,
    t: np.ndarray,
    prob: ProblemArrays,
    in2d: np.ndarray,
    in3d: np.ndarray,
    support: np.ndarray,
    settings: RefineSettings,
) -> tuple[float, float, float, int]:
    """The numbers of :func:`reference_jackknife` in one compiled call (one refinement per
    supporting reference with its rows left out, started at the full estimate, with
    ``settings.max_iterations`` in all).

    Returns:
        (jackknife position std, largest centre shift, largest rotation in degrees, index into
        ``support`` of the reference whose removal moves the pose most).
    """
    offsets = prob.offsets
    n = support.shape[0]
    c = -m3.t_vec(R, t)
    idx3d = np.flatnonzero(in3d)
    all2d = np.flatnonzero(in2d)
    # First Gauss-Newton step of every leave-one-out problem from one pass over the inliers:
    # at the full estimate, the normal equations without reference k are the full ones minus
    # k's share (H - H_k, g - g_k), so the step costs a 6x6 solve instead of a residual and
    # Jacobian pass per reference. The remaining iterations refine from there.
    Hp, gp = _pair_normal_equations(R, c, prob, all2d, idx3d, settings.loss_scale)
    Ht = np.zeros((6, 6))
    gt = np.zeros(6)
    for q in range(Hp.shape[0]):
        Ht += Hp[q]
        gt += gp[q]
    centres = np.empty((n, 3))
    mean = np.zeros(3)
    max_rot = 0.0
    eye = np.eye(3)
    free = np.zeros(6, dtype=np.bool_)
    rest = with_iterations(settings, max(settings.max_iterations - 1, 0))  # the first is the step above
    for i in range(n):
        k = support[i]
        keep = all2d[(all2d < offsets[k]) | (all2d >= offsets[k + 1])]
        R1, c1 = _first_step(R, c, Ht - Hp[k], gp[k] - gt, settings.max_iterations)
        Rk, tk, _, _, _ = refine_pose_core(
            StartPose(R1, c1, eye, free), prob, keep, idx3d, rest, np.bool_(False)
        )
        ck = -m3.t_vec(Rk, tk)
        for a in range(3):
            centres[i, a] = ck[a]
            mean[a] += ck[a] / n
        max_rot = max(max_rot, _rotation_deg(Rk, R))
    std, max_shift, worst = _centre_spread(centres, mean, c)
    return std, max_shift, max_rot, worst


def reference_jackknife(
    est,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    in3d: np.ndarray,
    max_iterations: int = 2,
    support: np.ndarray | None = None,
) -> Jackknife:
    """Refine the pose once per supporting reference with that reference's matches left out.

    2D-3D constraints (tracks, depth) stay in every refinement: they tie the query to world
    points, not to one reference. Each refinement starts at the full estimate, so a few
    Gauss-Newton steps reach the leave-one-out optimum (``max_iterations``). With fewer than
    3 supporting references nothing is left to compare and the spread is nan.

    Args:
        support: the supporting pairs when the caller has them (:func:`supporting_pairs`).

    References:
        Efron & Stein (1981), the jackknife estimate of variance; used here per reference
        because map-pose errors and wrong matches are correlated within a reference.
    """
    p = est.p
    support = supporting_pairs(p, in2d) if support is None else support
    n = len(support)
    if n < 3:
        return Jackknife(n, float("nan"), float("nan"), float("nan"), -1)
    std, shift, rot, worst = jackknife_kernel(
        np.ascontiguousarray(R),
        np.ascontiguousarray(t),
        p.arrays,
        in2d,
        in3d,
        np.asarray(support, dtype=np.int64),
        est.refine_settings(max_iterations),
    )
    return Jackknife(n, float(std), float(shift), float(rot), int(support[worst]))


def reference_jackknife_with_prior(
    est,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    in3d: np.ndarray,
    support: np.ndarray,
    max_iterations: int = 3,
) -> Jackknife:
    """:func:`reference_jackknife` for a pose refined under the map prior
    (:func:`planarloc.robust.map_prior.refine_with_map_prior`): each leave-one-out refinement
    minimises the same objective. The 2D-3D points stay in every refinement, as in
    :func:`reference_jackknife`: a point was triangulated from two map images whose poses agreed
    on it, and it ties the query to the world, not to one reference.
    """
    p = est.p
    n = len(support)
    if n < 3:
        return Jackknife(n, float("nan"), float("nan"), float("nan"), -1)
    c = -R.T @ t
    start = StartPose(np.ascontiguousarray(R), c, np.eye(3), np.zeros(6, dtype=np.bool_))
    settings = est.refine_settings(max_iterations)
    idx3d = np.flatnonzero(in3d)
    centres = np.empty((n, 3))
    max_rot = 0.0
    for i, k in enumerate(support):
        idx2d = np.flatnonzero(in2d & (p.pair != k))
        Rk, tk, *_ = refine_with_map_prior(start, p.arrays, idx2d, idx3d, settings)
        centres[i] = -Rk.T @ tk
        max_rot = max(
            max_rot, math.degrees(math.acos(min(1.0, max(-1.0, (float(np.sum(Rk * R)) - 1.0) / 2.0))))
        )
    dev = centres - centres.mean(axis=0)
    cov = (n - 1.0) / n * dev.T @ dev
    shifts = np.linalg.norm(centres - c, axis=1)
    worst = int(np.argmax(shifts))
    return Jackknife(
        n,
        float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0))),
        float(shifts[worst]),
        max_rot,
        int(support[worst]),
    )
