"""Perspective-three-point: the 6DoF absolute pose from three 2D-3D correspondences.

Used by the 6DoF hypothesis family when 2D-3D constraints exist (local structure from the
retrieved map images), as PoseLib's hybrid estimator samples P3P next to its 2D-2D solvers.
Not in the paper, whose constraints are all 2D-2D.

Grunert's formulation (J. A. Grunert 1841, as reviewed by Haralick, Lee, Ottenberg and Nölle,
"Review and analysis of solutions of the three point perspective pose estimation problem", IJCV
13(3), 1994, Sec. 2.1): with distances ``sᵢ`` from the centre to the points along the unit rays
``jᵢ``, the law of cosines gives three equations ``sᵢ² + sₖ² − 2 sᵢ sₖ cos θᵢₖ = |pᵢ − pₖ|²``;
with ``s₂ = u s₁``, ``s₃ = v s₁`` eliminating ``s₁`` and ``u`` leaves a quartic in ``v``
(Haralick eq. 9). Deviation: the quartic's coefficients are formed here by multiplying the
polynomials of the elimination (``u = N(v) / D(v)`` substituted into the (1, 2) equation)
instead of from the expanded closed form, its real roots come from the Sturm-sequence solver of
:mod:`planarloc.numerics.sturm`, each depth triple is polished by two Gauss-Newton steps on the
three distance equations, and the pose is the rigid motion between the two point triangles
(orthonormal frames built on both, exact for a consistent triangle).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array, plain_float64_pair, rays_invalid
from planarloc.numerics.sturm import real_roots_sturm

MAX_SOLUTIONS = 4


@njit(cache=True, error_model="numpy", inline="always")
def _poly_mul(a: np.ndarray, na: int, b: np.ndarray, nb: int, out: np.ndarray, scale: float) -> None:
    """``out += scale · a · b`` for ascending coefficient arrays of degrees na, nb."""
    for i in range(na + 1):
        for k in range(nb + 1):
            out[i + k] += scale * a[i] * b[k]


@njit(cache=True, error_model="numpy")
def _frame(a: np.ndarray, b: np.ndarray, c: np.ndarray, F: np.ndarray) -> bool:
    """Orthonormal frame (columns) of the triangle (a, b, c): e1 along b − a, e3 normal."""
    d1 = b - a
    d2 = c - a
    n1 = np.sqrt(np.sum(d1 * d1))
    e3 = np.array(
        [d1[1] * d2[2] - d1[2] * d2[1], d1[2] * d2[0] - d1[0] * d2[2], d1[0] * d2[1] - d1[1] * d2[0]]
    )
    n3 = np.sqrt(np.sum(e3 * e3))
    if not (n1 > 1e-12 and n3 > 1e-12 * n1 * np.sqrt(np.sum(d2 * d2))):
        return False
    e1 = d1 / n1
    e3 = e3 / n3
    e2 = np.array(
        [e3[1] * e1[2] - e3[2] * e1[1], e3[2] * e1[0] - e3[0] * e1[2], e3[0] * e1[1] - e3[1] * e1[0]]
    )
    for i in range(3):
        F[i, 0], F[i, 1], F[i, 2] = e1[i], e2[i], e3[i]
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _refine_depths(s: np.ndarray, ca: float, cb: float, cg: float, d2: np.ndarray) -> None:
    """Two Gauss-Newton steps on the depths ``s`` (3,) of the law of cosines
    f_ik(s) = s_i² + s_k² − 2 s_i s_k cos θ_ik − d_ik², (i, k) = (2,3), (1,3), (1,2);
    ``d2`` = (a², b², c²)."""
    a2, b2, c2 = d2[0], d2[1], d2[2]
    for _ in range(2):
        f0 = s[1] * s[1] + s[2] * s[2] - 2.0 * s[1] * s[2] * ca - a2
        f1 = s[0] * s[0] + s[2] * s[2] - 2.0 * s[0] * s[2] * cb - b2
        f2 = s[0] * s[0] + s[1] * s[1] - 2.0 * s[0] * s[1] * cg - c2
        # J = [[0, p, q], [r, 0, w], [y, z, 0]] solved by Cramer's rule (numba's LAPACK
        # bindings cost seconds of compile time for a 3x3 system).
        p_, q_ = 2.0 * (s[1] - s[2] * ca), 2.0 * (s[2] - s[1] * ca)
        r_, w_ = 2.0 * (s[0] - s[2] * cb), 2.0 * (s[2] - s[0] * cb)
        y_, z_ = 2.0 * (s[0] - s[1] * cg), 2.0 * (s[1] - s[0] * cg)
        det = p_ * w_ * y_ + q_ * r_ * z_
        if not abs(det) > 1e-12 * (s[0] * s[1] * s[2] + 1e-300):
            break
        s[0] -= (-f0 * w_ * z_ + p_ * w_ * f2 + q_ * f1 * z_) / det
        s[1] -= (f0 * w_ * y_ + q_ * r_ * f2 - q_ * f1 * y_) / det
        s[2] -= (-p_ * r_ * f2 + p_ * f1 * y_ + f0 * r_ * z_) / det


@njit(cache=True, error_model="numpy", inline="always")
def _add_pose(
    j: np.ndarray, s: np.ndarray, X: np.ndarray, Fw: np.ndarray, Rs: np.ndarray, ts: np.ndarray, count: int
) -> int:
    """Write the pose that puts ray i at depth s[i] onto X[i] at ``count`` unless degenerate or a
    duplicate; returns the new count."""
    P = np.empty((3, 3))
    for i in range(3):
        for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            P[i, a] = s[i] * j[i, a]
    Fc = np.empty((3, 3))
    if not _frame(P[0], P[1], P[2], Fc):
        return count
    R = m3.mul_t(Fc, Fw)
    t = P[0] - m3.vec(R, X[0])
    for m in range(count):
        if np.sum(np.abs(Rs[m] - R)) < 1e-9 and np.sum(np.abs(ts[m] - t)) < 1e-9 * (1.0 + np.sum(np.abs(t))):
            return count
    m3.store_pose(Rs, ts, count, R, t)
    return count + 1


@njit(cache=True, error_model="numpy")
def solve_p3p(x: np.ndarray, X: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> int:
    """Core solver: x (3, 3) rays (any length), X (3, 3) world points; writes ≤ 4 poses.

    ``Rs`` (4, 3, 3), ``ts`` (4, 3) receive ``cam_from_world`` with ``x ∝ R X + t`` and every
    point in front of the camera. Returns the number of solutions (0: collinear points,
    coincident rays, or no real solution).
    """
    j = np.empty((3, 3))
    for i in range(3):
        n = np.sqrt(x[i, 0] ** 2 + x[i, 1] ** 2 + x[i, 2] ** 2)
        if not n > 0.0:
            return 0
        for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
            j[i, a] = x[i, a] / n
    d2 = np.array([np.sum((X[1] - X[2]) ** 2), np.sum((X[0] - X[2]) ** 2), np.sum((X[0] - X[1]) ** 2)])
    a2, b2, c2 = d2[0], d2[1], d2[2]
    if not (a2 > 1e-24 and b2 > 1e-24 and c2 > 1e-24):
        return 0
    ca = np.sum(j[1] * j[2])  # cos α: rays 2, 3
    cb = np.sum(j[0] * j[2])  # cos β: rays 1, 3
    cg = np.sum(j[0] * j[1])  # cos γ: rays 1, 2
    q = (a2 - c2) / b2
    r = c2 / b2
    # u = N(v) / D(v) (Haralick eq. 8), substituted into u² − 2u cos γ + 1 − r (1 + v² − 2 v cos β) = 0
    # times D²: N² − 2 cos γ N D + (1 − r (1 + v² − 2 v cos β)) D² = 0, a quartic in v.
    N = np.array([1.0 + q, -2.0 * q * cb, q - 1.0])
    D = np.array([2.0 * cg, -2.0 * ca])
    W = np.array([1.0 - r, 2.0 * r * cb, -r])
    D2 = np.zeros(3)
    _poly_mul(D, 1, D, 1, D2, 1.0)
    quartic = np.zeros(5)
    _poly_mul(N, 2, N, 2, quartic, 1.0)
    _poly_mul(N, 2, D, 1, quartic, -2.0 * cg)
    _poly_mul(W, 2, D2, 2, quartic, 1.0)
    roots = np.empty(4)
    nr = real_roots_sturm(quartic, roots)
    Fw = np.empty((3, 3))
    if not _frame(X[0], X[1], X[2], Fw):
        return 0
    s = np.empty(3)
    count = 0
    for k in range(nr):
        v = roots[k]
        den = D[0] + D[1] * v
        g = 1.0 + v * v - 2.0 * v * cb
        if abs(den) < 1e-12 or not g > 0.0:
            continue
        u = (N[0] + N[1] * v + N[2] * v * v) / den
        s1 = np.sqrt(b2 / g)
        s[0], s[1], s[2] = s1, u * s1, v * s1
        if not (s[1] > 0.0 and s[2] > 0.0):
            continue
        _refine_depths(s, ca, cb, cg, d2)
        if not (s[0] > 0.0 and s[1] > 0.0 and s[2] > 0.0):
            continue
        count = _add_pose(j, s, X, Fw, Rs, ts, count)
        if count == MAX_SOLUTIONS:
            break
    return count


@njit(cache=True, error_model="numpy")
def _poses(x: np.ndarray, X: np.ndarray, out: np.ndarray) -> int:
    """Validated single call: -1 unless x, X are (3, 3) and finite, else the number of poses
    written as ``out[k, :3] = R``, ``out[k, 3] = t`` into out (4, 4, 3)."""
    if rays_invalid(x, X, 3, 3, True):
        return -1
    Rs = np.empty((MAX_SOLUTIONS, 3, 3))
    ts = np.empty((MAX_SOLUTIONS, 3))
    n = solve_p3p(x, X, Rs, ts)
    for k in range(n):
        out[k, :3] = Rs[k]
        out[k, 3] = ts[k]
    return n


def abspose_p3p(x_query: object, points: object) -> list[Pose]:
    """Query poses ``cam_from_world`` from three 2D-3D correspondences.

    Args:
        x_query: (3, 3) query rays, e.g. normalized homogeneous points ``(x, y, 1)`` (any
            non-zero length; not necessarily z = 1, so fisheye bearings work too).
        points: (3, 3) the corresponding world points.

    Returns:
        Up to 4 poses with every point in front of the camera; empty when the points are
        collinear or coincident, or no real solution exists.

    Raises:
        InputError: wrong shapes, NaN/inf entries or an all-zero ray.

    Example:
        >>> import numpy as np
        >>> X = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 6.0], [0.0, 1.0, 4.0]])
        >>> poses = abspose_p3p(X / X[:, 2:], X)     # the identity pose is among them
        >>> min(float(np.abs(p.R - np.eye(3)).max() + np.abs(p.t).max()) for p in poses) < 1e-9
        True
    """
    out = np.empty((MAX_SOLUTIONS, 4, 3))
    pair = plain_float64_pair(x_query, points, 3)
    n = _poses(*pair, out) if pair is not None else -1
    if n == -1:
        n = _poses(check_array("x_query", x_query, (3, 3)), check_array("points", points, (3, 3)), out)
        if n == -1:
            raise InputError("x_query: a ray is all zero; expected three non-zero query rays")
    return Pose._from_buffer(out, n)
