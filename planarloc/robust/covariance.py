"""The covariance a judged pose reports: its position's, from every source of error
(:func:`position_covariance`), and the (6, 6) of ``world_from_camera`` in ROS order
(:func:`pose_covariance`). :mod:`planarloc.robust.verification` raises the std further by its
checks and keeps the larger one.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planarloc.geometry.mat3 import sym_eigvals
from planarloc.numerics.cholesky import cholesky_factor, spd_inverse
from planarloc.robust import observability as obs
from planarloc.robust.final_refinement import RefinedPose
from planarloc.robust.options import RansacOptions


def position_covariance(
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
