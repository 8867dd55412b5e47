"""The final refinement of a search's pose: refined on its inliers until they stop changing.

With 2D-3D constraints and a map pose uncertainty the reference poses are refined too, as
nuisance parameters under the map prior (:mod:`planarloc.robust.map_prior`); otherwise the query
pose alone (:func:`planarloc.robust.refinement.refine_pose`, the paper's 2D-2D mode, whose
map-error share of the uncertainty is propagated afterwards).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.robust.map_prior import refine_with_map_prior
from planarloc.robust.refinement import refine_pose
from planarloc.robust.scoring import errors_sq

LATER_ROUND_ITERATIONS = 3  # LM iterations of the rounds after the first in refine_until_stable


@njit(cache=True, error_model="numpy")
def refine_until_stable(
    Rq: np.ndarray, tq: np.ndarray, xq: np.ndarray, xr: np.ndarray, pair: np.ndarray, offsets: np.ndarray,
    f_query: np.ndarray, f_ref: np.ndarray, ref_R: np.ndarray, ref_t: np.ndarray,
    xq3d: np.ndarray, X3d: np.ndarray, inlier_threshold_sq: float, loss_scale: float, max_iterations: int,
    rounds: int, sigma_floor: float, map_rotation_std_rad: float = 0.0, map_position_std_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, np.ndarray, np.ndarray, float, float]:
    """The final refinement: :func:`refine_pose` on the inliers of the current pose, repeated on
    the refined pose's inliers while they change (at most ``rounds`` times), in one call.

    Args:
        Rq, tq: the RANSAC winner ``query_from_world``.
        inlier_threshold_sq: τ² (pixels²) defining the inliers.
        max_iterations: LM iterations of the first round (0: only evaluate H and the cost at
            the pose); later rounds take at most ``LATER_ROUND_ITERATIONS``.
        rounds: at most this many refinements (≥ 1).
        map_rotation_std_rad, map_position_std_m: the map prior; when either is > 0 and the
            problem has 2D-3D inliers, :func:`refine_with_map_prior` refines (H is then the
            marginal information of the query pose).

    Returns:
        R, t, H, σ̂, robust cost (as :func:`refine_pose`), the inlier masks (N,), (M,) at the
        returned pose, its MSAC cost ``Σ min(e², τ²)`` (the score every search is judged by) and
        the 2D-3D constraints' share of that cost.
    """
    R, t = Rq.copy(), tq.copy()
    e2d, e3d = errors_sq(R, t, xq, xr, offsets, f_query, f_ref, ref_R, ref_t, xq3d, X3d)
    in2d = e2d < inlier_threshold_sq
    in3d = e3d < inlier_threshold_sq
    eye = np.eye(3)
    free = np.zeros(6, dtype=np.bool_)
    prior = map_rotation_std_rad > 0.0 or map_position_std_m > 0.0
    H = np.zeros((6, 6))
    sigma = np.inf
    cost = np.inf
    for rnd in range(max(rounds, 1)):
        # Later rounds start at an optimum whose inlier set changed by a few matches: a couple of
        # iterations reach the new one (the first round may start a few pixels away).
        its = max_iterations if rnd == 0 else min(max_iterations, LATER_ROUND_ITERATIONS)
        if prior and in3d.any():
            R, t, H, sigma, cost = refine_with_map_prior(R, t, xq, xr, pair, np.flatnonzero(in2d), f_query, f_ref,
                                                         ref_R, ref_t, xq3d, X3d, np.flatnonzero(in3d), loss_scale,
                                                         its, sigma_floor, map_rotation_std_rad, map_position_std_m,
                                                         -m3.t_vec(R, t), eye, free)
        else:
            R, t, H, sigma, cost = refine_pose(R, t, xq, xr, pair, np.flatnonzero(in2d), f_query, f_ref, ref_R,
                                               ref_t, xq3d, X3d, np.flatnonzero(in3d), loss_scale, its,
                                               sigma_floor, -m3.t_vec(R, t), eye, free)
        e2d, e3d = errors_sq(R, t, xq, xr, offsets, f_query, f_ref, ref_R, ref_t, xq3d, X3d)
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
    return R, t, H, sigma, cost, in2d, in3d, msac2d + msac3d, msac3d
