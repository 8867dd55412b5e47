"""Upright 2-point absolute pose (P2P with known vertical), used by the ``tracks`` mode.

Not in the paper: when 3D points are available (triangulated tracks or reference depth),
two 2D-3D correspondences fix the query pose relative to an upright reference frame —
yaw ``θ`` about y and a 3D translation (Kukelova, Bujnak, Pajdla, "Closed-form solutions to
minimal absolute pose problems with known vertical direction", ACCV 2010). Our derivation:
with ``λᵢ xᵢ = R_y(θ) Xᵢ + t``, subtracting the two gives ``λ₁x₁ − λ₂x₂ = R_y(θ) d``,
``d = X₁ − X₂``, so ``R_y(θ) d`` lies in the plane of the two rays:
``nᵀ R_y(θ) d = 0`` with ``n = x₁ × x₂`` — one trigonometric equation
``a cos θ + b sin θ + e = 0`` with up to two solutions; depths by least squares and
``t = λ₁x₁ − R_y(θ) X₁``. Solutions with a non-positive depth are discarded.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import check_array, plain_float64_pair, rays_invalid


@njit(cache=True, error_model="numpy")
def solve_up2p(x: np.ndarray, X: np.ndarray, thetas: np.ndarray, ts: np.ndarray) -> int:
    """Core solver: x (2, 3) rays, X (2, 3) points in the upright frame; writes ≤ 2 solutions.

    ``thetas`` (2,) receives yaw angles with ``R = R_y(θ)`` of eq. (1) of the paper, ``ts``
    (2, 3) the translations (``x ∝ R X + t``). Returns the number of solutions.
    """
    n0 = x[0, 1] * x[1, 2] - x[0, 2] * x[1, 1]
    n1 = x[0, 2] * x[1, 0] - x[0, 0] * x[1, 2]
    n2 = x[0, 0] * x[1, 1] - x[0, 1] * x[1, 0]
    d0, d1, d2 = X[0, 0] - X[1, 0], X[0, 1] - X[1, 1], X[0, 2] - X[1, 2]
    nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    dd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if not (nn > 1e-12 and dd > 1e-12):
        return 0  # identical rays or identical points
    # With R_y(θ) d = (c d0 - s d2, d1, s d0 + c d2):  a c + b s + e = 0.
    a = n0 * d0 + n2 * d2
    b = n2 * d0 - n0 * d2
    e = n1 * d1
    r = np.sqrt(a * a + b * b)
    if r < 1e-12 * nn * dd or abs(e) > r:
        return 0
    psi = np.arctan2(b, a)
    delta = np.arccos(-e / r)
    count = 0
    for sgn in (1.0, -1.0):
        if sgn < 0 and delta < 1e-12:
            break
        th = psi + sgn * delta
        c, s = np.cos(th), np.sin(th)
        # R X_i for both points
        RX00 = c * X[0, 0] - s * X[0, 2]
        RX01 = X[0, 1]
        RX02 = s * X[0, 0] + c * X[0, 2]
        Rd0, Rd1, Rd2 = c * d0 - s * d2, d1, s * d0 + c * d2
        # λ1 x1 - λ2 x2 = R d  (least squares)
        aa = x[0, 0] ** 2 + x[0, 1] ** 2 + x[0, 2] ** 2
        bb = x[1, 0] ** 2 + x[1, 1] ** 2 + x[1, 2] ** 2
        ab = x[0, 0] * x[1, 0] + x[0, 1] * x[1, 1] + x[0, 2] * x[1, 2]
        ad = x[0, 0] * Rd0 + x[0, 1] * Rd1 + x[0, 2] * Rd2
        bd = x[1, 0] * Rd0 + x[1, 1] * Rd1 + x[1, 2] * Rd2
        det = aa * bb - ab * ab
        if det <= 1e-12 * aa * bb:
            continue
        l1 = (bb * ad - ab * bd) / det
        l2 = (ab * ad - aa * bd) / det
        if l1 <= 0 or l2 <= 0:
            continue
        thetas[count] = np.arctan2(s, c)
        ts[count, 0] = l1 * x[0, 0] - RX00
        ts[count, 1] = l1 * x[0, 1] - RX01
        ts[count, 2] = l1 * x[0, 2] - RX02
        count += 1
    return count


@njit(cache=True, error_model="numpy")
def _poses(x: np.ndarray, X: np.ndarray, out: np.ndarray) -> int:
    """Validated single call: -1 unless x, X are (2, 3) and finite, else the number of poses
    written as ``out[k, :3] = R_y(θ)`` (eq. 1 of the paper), ``out[k, 3] = t`` into out (2, 4, 3)."""
    if rays_invalid(x, X, 2, 2, False):
        return -1
    th = np.empty(2)
    ts = np.empty((2, 3))
    n = solve_up2p(x, X, th, ts)
    for k in range(n):
        c, s = np.cos(th[k]), np.sin(th[k])
        out[k, 0, 0], out[k, 0, 1], out[k, 0, 2] = c, 0.0, -s
        out[k, 1, 0], out[k, 1, 1], out[k, 1, 2] = 0.0, 1.0, 0.0
        out[k, 2, 0], out[k, 2, 1], out[k, 2, 2] = s, 0.0, c
        out[k, 3, 0], out[k, 3, 1], out[k, 3, 2] = ts[k, 0], ts[k, 1], ts[k, 2]
    return n


def abspose_up2p(x_query: object, points: object) -> list[Pose]:
    """Upright poses ``query_from_frame`` from two 2D-3D correspondences.

    Args:
        x_query: (2, 3) normalized homogeneous query points (camera y = gravity).
        points: (2, 3) the 3D points in an upright frame (its y-axis = gravity), e.g. a
            reference camera's frame under local planar motion.

    Returns:
        Up to 2 poses with ``R = R_y(θ)`` placing both points in front of the query; empty
        when degenerate (identical rays or points, no real solution).
    """
    out = np.empty((2, 4, 3))
    pair = plain_float64_pair(x_query, points, 2)
    n = _poses(*pair, out) if pair is not None else -1
    if n == -1:  # not a plain float64 array, or invalid: convert, or raise the usual message
        n = _poses(check_array("x_query", x_query, (2, 3)), check_array("points", points, (2, 3)), out)
    return Pose._from_buffer(out, n)
