"""Local optimisation of absolute-pose hypotheses: which ones, and how (numba).

The generic loop (:mod:`planarloc.robust.ransac`) refines a batch's best hypothesis and its
distinct near-ties; for absolute poses "distinct" is a centre test
(:func:`distinct_centres`) and the refinement is :func:`refine_planar_then_6dof`: a few
Levenberg-Marquardt iterations in the planar model's 3 DoF, then in 6DoF, each on the
inliers of a widened threshold, in one compiled call (a Python round trip per stage cost
more than the iterations themselves at 3 × 20 matches).

References: LO-RANSAC (Chum, Matas, Kittler, DAGM 2003) for refining the best-so-far
model on its inliers; here the inner refinement is the robust one of
:func:`planarloc.robust.refinement.refine_pose` rather than an inner RANSAC.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.robust.problem import ProblemArrays
from planarloc.robust.refinement import RefineSettings, StartPose, refine_pose_core, with_iterations
from planarloc.robust.scoring import errors_sq

# Planar motion in refine_pose's parameters (rotation increment Exp(δ) R in the camera frame,
# centre c0 + B p): only the yaw δ1 about the camera y axis and the centre within the plane
# spanned by B[:, 0], B[:, 2] move.
PLANAR_FIXED = np.array([True, False, True, False, True, False])
_FREE = np.zeros(6, dtype=np.bool_)


@njit(cache=True, error_model="numpy")
def level_plane(ref_R: np.ndarray, cos_tolerance: float) -> np.ndarray:
    """Orthonormal basis of the world whose column 1 is the references' common y axis.

    Args:
        ref_R: (P, 3, 3) rotations of ``ref_from_world``; row 1 of each is the reference's
            y axis (down, for an upright camera) in world coordinates.
        cos_tolerance: cosine of the largest angle allowed between any reference's y axis
            and their mean.

    Returns:
        (3, 3) basis ``B`` (columns: a level direction, the mean y axis, the other level
        direction), or a (0, 3) array when the references are not level with each other.
    """
    g = np.zeros(3)
    for p in range(ref_R.shape[0]):
        g += ref_R[p, 1]
    g /= np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    for p in range(ref_R.shape[0]):
        if ref_R[p, 1, 0] * g[0] + ref_R[p, 1, 1] * g[1] + ref_R[p, 1, 2] * g[2] < cos_tolerance:
            return np.zeros((0, 3))
    e = np.zeros(3)
    e[np.argmin(np.abs(g))] = 1.0  # the world axis most orthogonal to g
    u = np.array([g[1] * e[2] - g[2] * e[1], g[2] * e[0] - g[0] * e[2], g[0] * e[1] - g[1] * e[0]])
    u /= np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    v = np.array([u[1] * g[2] - u[2] * g[1], u[2] * g[0] - u[0] * g[2], u[0] * g[1] - u[1] * g[0]])
    B = np.empty((3, 3))
    for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
        B[a, 0], B[a, 1], B[a, 2] = u[a], g[a], v[a]
    return B


@njit(cache=True, error_model="numpy")
def distinct_centres(R: np.ndarray, t: np.ndarray, cb: np.ndarray, ref_centres: np.ndarray) -> np.ndarray:
    """Which hypotheses are other models than the one with centre ``cb``.

    Args:
        R, t: (n, 3, 3), (n, 3) hypotheses ``query_from_world``.
        cb: (3,) centre of the reference model, world frame.
        ref_centres: (P, 3) reference camera centres, world frame.

    Returns:
        (n,) bool: the hypothesis' centre is farther from ``cb`` than 10 % of its distance to
        the nearest reference centre (the scatter of correct hypotheses is not; a pose slid
        along a weakly observed direction is).
    """
    out = np.empty(R.shape[0], dtype=np.bool_)
    for i in range(R.shape[0]):
        c = -m3.t_vec(R[i], t[i])
        d_min = np.inf
        for p in range(ref_centres.shape[0]):
            d0, d1, d2 = ref_centres[p, 0] - c[0], ref_centres[p, 1] - c[1], ref_centres[p, 2] - c[2]
            d_min = min(d_min, d0 * d0 + d1 * d1 + d2 * d2)
        e0, e1, e2 = c[0] - cb[0], c[1] - cb[1], c[2] - cb[2]
        out[i] = e0 * e0 + e1 * e1 + e2 * e2 > 0.01 * d_min
    return out


class LocalOptimization(NamedTuple):
    """The settings of :func:`refine_planar_then_6dof` for one problem, as one record.

    Attributes:
        refine: the 6DoF stage's :class:`~planarloc.robust.refinement.RefineSettings`; its
            inlier threshold (squared pixel error under which a datum is refined on) and loss
            scale serve the planar stage too, and its σ̂ floor has no effect on the pose.
        planar_iterations: LM iterations of the planar stage.
        level: (3, 3) from :func:`level_plane`, or (0, 3) for no planar stage.
        cos_level: the planar stage runs when the hypothesis' camera y axis is within
            ``arccos(cos_level)`` of ``level[:, 1]``.
        max_data: the planar stage refines on every s-th inlier, s = ⌈inliers / max_data⌉ (its
            cost is linear in the data, and reaching the basin needs a hundred, not a
            thousand); the 6DoF stage on all of them, so that the final refinement starts
            converged.
    """

    refine: RefineSettings
    planar_iterations: int
    level: np.ndarray
    cos_level: float
    max_data: int


@njit(cache=True, error_model="numpy")
def _refine_stage(
    R: np.ndarray, t: np.ndarray, prob: ProblemArrays, lo: LocalOptimization, planar: np.bool_
) -> tuple[np.ndarray, np.ndarray]:
    """One stage of :func:`refine_planar_then_6dof` on the inliers of ``(R, t)``: ``planar``, yaw
    and the centre within the level plane on at most about ``lo.max_data`` of them; else 6DoF
    on all of them. Returns the input when fewer than 6 inliers."""
    s = lo.refine
    if planar:
        settings = with_iterations(s, lo.planar_iterations)
        B, fixed, max_data = lo.level, PLANAR_FIXED, lo.max_data
    else:
        settings, B, fixed, max_data = s, np.eye(3), _FREE, 1 << 62
    e2d, e3d = errors_sq(R, t, prob)
    idx2d = np.flatnonzero(e2d < s.inlier_threshold_sq)
    idx3d = np.flatnonzero(e3d < s.inlier_threshold_sq)
    n = idx2d.shape[0] + idx3d.shape[0]
    if n < 6:
        return R, t
    stride = (n + max_data - 1) // max_data
    if stride > 1:
        idx2d, idx3d = idx2d[::stride].copy(), idx3d[::stride].copy()
    # Only the pose is wanted: no normal matrix after the last step. ``fixed`` copied: writable,
    # typed as in every other StartPose (refine_pose's one signature).
    start = StartPose(R, -m3.t_vec(R, t), B, fixed.copy())
    refined = refine_pose_core(start, prob, idx2d, idx3d, settings, np.bool_(False))
    return refined.R, refined.t


@njit(cache=True, error_model="numpy")
def refine_planar_then_6dof(
    Rq: np.ndarray, tq: np.ndarray, prob: ProblemArrays, lo: LocalOptimization
) -> tuple[np.ndarray, np.ndarray]:
    """Local optimisation of one hypothesis: planar, then 6DoF robust refinement on its inliers.

    Stage 1 (only when ``lo.level`` is a basis and the hypothesis' camera y axis ``Rq[1]`` is
    within ``arccos(lo.cos_level)`` of ``lo.level[:, 1]``, i.e. a planar hypothesis of references
    level with each other): ``lo.planar_iterations`` LM iterations of :func:`refine_pose` moving
    only the yaw and the centre within the level plane, on the matches whose error is below the
    inlier threshold. With few inliers and outliers let in by a widened threshold, the 3 extra
    DoF of a 6DoF step absorb outliers as tilt and height; the planar step cannot. Stage 2:
    ``lo.refine.max_iterations`` 6DoF iterations on the inliers of the stage-1 pose (same
    threshold), so a slightly non-planar truth is still reached.

    Args:
        Rq, tq: (3, 3), (3,) hypothesis ``query_from_world``.
        prob: the problem's arrays (:attr:`planarloc.robust.problem.AbsolutePoseProblem.arrays`).
        lo: the settings (:class:`LocalOptimization`).

    Returns:
        the refined (R (3, 3), t (3,)); the input when fewer than 6 inliers.
    """
    R, t = Rq.copy(), tq.copy()
    level = lo.level
    if (
        lo.planar_iterations > 0
        and level.shape[0] == 3
        and (R[1, 0] * level[0, 1] + R[1, 1] * level[1, 1] + R[1, 2] * level[2, 1]) > lo.cos_level
    ):
        R, t = _refine_stage(R, t, prob, lo, np.bool_(True))  # typed, not literals: one compiled signature
    return _refine_stage(R, t, prob, lo, np.bool_(False))
