"""Planar 2-point relative pose (paper Sec. IV-A, eq. 3-11).

Under local planar motion (rotation about the camera y-axis, translation in x-z), the
essential matrix has the sparse form of eq. (2)::

    E = [[0, e01, 0], [e10, 0, e12], [0, e21, 0]]
      = ρ [[0, cos(θ-φ), 0], [-cos φ, 0, sin φ], [0, sin(θ-φ), 0]]

Each match gives one linear equation in ``e = (e01, e10, e12, e21)`` (eq. 4-5, 8):
``x_r0 x_q1 e01 + x_r1 x_q0 e10 + x_r1 x_q2 e12 + x_r2 x_q1 e21 = 0``; two matches leave a
2-D null space (eq. 9). The paper then imposes the two unit-circle constraints of eq. (10)
on ``x = e / ρ``; since ``ρ`` is free these reduce to the single homogeneous quadratic
``e01² + e21² = e10² + e12²``. On the null space it is a 2x2 quadratic form whose two
isotropic directions we obtain in closed form from its eigen-decomposition — a
numerically stable replacement of the authors' "solve then filter with the trace
constraint" (their MATLAB code), giving at most 2 essential matrices. ``θ`` and ``φ`` follow
from eq. (11); the sign of ``t`` (``φ`` vs ``φ + π``) is fixed by the cheirality test. The
180° "twisted pair" of a general essential matrix is never planar, so it does not arise.

Degenerate input returns no solution: repeated matches (rank-1 system), matches on the
horizon line in both views (no constraint), and zero baseline / points at infinity (the
quadratic form vanishes on the whole null space, so every direction fits).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array, plain_float64_pair

_EPS_RANK = 1e-9
_EPS_FORM = 1e-12


@njit(cache=True, inline="always", error_model="numpy")
def planar_depth_sign(
    ct: float,
    st: float,
    sp: float,
    cp: float,
    q0: float,
    q1: float,
    q2: float,
    r0: float,
    r1: float,
    r2: float,
) -> int:
    """+1 if the match ``(q, r)`` is in front of both cameras for (θ, φ), -1 for (θ, φ + π), 0 for
    neither, 2 for parallel rays (a point at infinity or on the baseline). ``ct, st = cos θ,
    sin θ``; ``sp, cp = sin φ, cos φ``.

    Midpoint depths of ``λ_r x_r ≈ λ_q R x_q + t`` with ``t = -R_y(θ) [sin φ, 0, cos φ]`` (eq. 1).
    """
    t0 = -(ct * sp - st * cp)
    t2 = -(st * sp + ct * cp)
    a0 = ct * q0 - st * q2
    a1 = q1
    a2 = st * q0 + ct * q2
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = r0 * r0 + r1 * r1 + r2 * r2
    ab = a0 * r0 + a1 * r1 + a2 * r2
    at = a0 * t0 + a2 * t2
    bt = r0 * t0 + r2 * t2
    det = aa * bb - ab * ab
    if det <= 1e-12 * aa * bb:
        return 2
    lq = (-at * bb + ab * bt) / det
    lr = (aa * bt - ab * at) / det
    if lq > 0 and lr > 0:
        return 1
    if lq < 0 and lr < 0:
        return -1
    return 0


@njit(cache=True, inline="always", error_model="numpy")
def _depth_signs(c: float, s: float, sp: float, cp: float, xq: np.ndarray, xr: np.ndarray) -> int:
    """+1 if both matches have positive depths for (θ, φ), -1 if for (θ, φ + π), 0 if
    neither, 2 if a match has parallel rays (a point at infinity: no depth information).

    ``c, s = cos θ, sin θ`` and ``sp, cp = sin φ, cos φ``; per match :func:`planar_depth_sign`.
    """
    sign = 0
    for k in range(2):
        s_k = planar_depth_sign(c, s, sp, cp, xq[k, 0], xq[k, 1], xq[k, 2], xr[k, 0], xr[k, 1], xr[k, 2])
        if s_k == 2 or s_k == 0:
            return s_k
        if sign == 0:
            sign = s_k
        elif sign != s_k:
            return 0
    return sign


_ZERO4 = (0.0, 0.0, 0.0, 0.0)


@njit(cache=True, error_model="numpy", inline="always")
def _system_rows(xq: np.ndarray, xr: np.ndarray):
    """``(ok, r, s)``: the two rows of the 2x4 system A e = 0 (eq. 8), normalised; not ok for a
    match on the horizon line of both views (it constrains nothing) or NaN."""
    r0 = xr[0, 0] * xq[0, 1]
    r1 = xr[0, 1] * xq[0, 0]
    r2 = xr[0, 1] * xq[0, 2]
    r3 = xr[0, 2] * xq[0, 1]
    s0 = xr[1, 0] * xq[1, 1]
    s1 = xr[1, 1] * xq[1, 0]
    s2 = xr[1, 1] * xq[1, 2]
    s3 = xr[1, 2] * xq[1, 1]
    nr = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    ns = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
    if not (nr > 1e-300 and ns > 1e-300):
        return False, _ZERO4, _ZERO4
    return True, (r0 / nr, r1 / nr, r2 / nr, r3 / nr), (s0 / ns, s1 / ns, s2 / ns, s3 / ns)


@njit(cache=True, error_model="numpy", inline="always")
def _null_space(r, s):
    """``(ok, n1, n2)``: an orthonormal basis of the null space of rows r, s (eq. 9), from the
    Hodge dual of r ∧ s (its rows are orthogonal to r and s); not ok at rank 1."""
    r0, r1, r2, r3 = r
    s0, s1, s2, s3 = s
    p01 = r0 * s1 - r1 * s0
    p02 = r0 * s2 - r2 * s0
    p03 = r0 * s3 - r3 * s0
    p12 = r1 * s2 - r2 * s1
    p13 = r1 * s3 - r3 * s1
    p23 = r2 * s3 - r3 * s2
    if p01 * p01 + p02 * p02 + p03 * p03 + p12 * p12 + p13 * p13 + p23 * p23 < _EPS_RANK * _EPS_RANK:
        return False, _ZERO4, _ZERO4  # rank 1: repeated or proportional matches
    # Candidate null vectors (dual rows); take the longest, then Gram-Schmidt the next.
    c = ((0.0, p23, -p13, p12), (-p23, 0.0, p03, -p02), (p13, -p03, 0.0, p01), (-p12, p02, -p01, 0.0))
    best, ib = -1.0, 0
    for i in range(4):
        ni = c[i][0] ** 2 + c[i][1] ** 2 + c[i][2] ** 2 + c[i][3] ** 2
        if ni > best:
            best, ib = ni, i
    nb = np.sqrt(best)
    a0, a1, a2, a3 = c[ib][0] / nb, c[ib][1] / nb, c[ib][2] / nb, c[ib][3] / nb
    best2 = -1.0
    b0 = b1 = b2 = b3 = 0.0
    for i in range(4):
        d = c[i][0] * a0 + c[i][1] * a1 + c[i][2] * a2 + c[i][3] * a3
        w0, w1, w2, w3 = c[i][0] - d * a0, c[i][1] - d * a1, c[i][2] - d * a2, c[i][3] - d * a3
        nw = w0 * w0 + w1 * w1 + w2 * w2 + w3 * w3
        if nw > best2:
            best2, b0, b1, b2, b3 = nw, w0, w1, w2, w3
    nb2 = np.sqrt(best2)
    return True, (a0, a1, a2, a3), (b0 / nb2, b1 / nb2, b2 / nb2, b3 / nb2)


@njit(cache=True, error_model="numpy", inline="always")
def _isotropic_basis(n1, n2):
    """``(ok, v1, v2, mu1, mu2)`` for the quadratic form of e01² + e21² − e10² − e12² on the
    null space: its eigenvectors v1 (eigenvalue mu2²) and v2 (eigenvalue −mu1²); the form
    vanishes on ``mu1 v1 ± mu2 v2``. Not ok if the form vanishes (zero baseline, points at
    infinity) or is definite (no real solution)."""
    p = n1[0] * n1[0] - n1[1] * n1[1] - n1[2] * n1[2] + n1[3] * n1[3]
    r = n2[0] * n2[0] - n2[1] * n2[1] - n2[2] * n2[2] + n2[3] * n2[3]
    q = n1[0] * n2[0] - n1[1] * n2[1] - n1[2] * n2[2] + n1[3] * n2[3]
    mean = 0.5 * (p + r)
    dev = np.sqrt(0.25 * (p - r) ** 2 + q * q)
    lam1 = mean + dev
    lam2 = mean - dev
    if (dev < _EPS_FORM and abs(mean) < _EPS_FORM) or lam2 > _EPS_FORM or lam1 < -_EPS_FORM:
        return False, (0.0, 0.0), (0.0, 0.0), 0.0, 0.0
    lam1 = max(lam1, 0.0)
    lam2 = min(lam2, 0.0)
    # Eigenvector of lam1 (choose the better-conditioned of two formulas).
    va0, va1 = q, lam1 - p
    vb0, vb1 = lam1 - r, q
    if va0 * va0 + va1 * va1 >= vb0 * vb0 + vb1 * vb1:
        v10, v11 = va0, va1
    else:
        v10, v11 = vb0, vb1
    nv = np.sqrt(v10 * v10 + v11 * v11)
    if nv < 1e-300:  # p == r and q == 0: isotropic form, already excluded unless lam1 == lam2
        v10, v11 = 1.0, 0.0
    else:
        v10, v11 = v10 / nv, v11 / nv
    return True, (v10, v11), (-v11, v10), np.sqrt(-lam2), np.sqrt(lam1)


@njit(cache=True, error_model="numpy", inline="always")
def _write_solution(l1, l2, n1, n2, xq, xr, thetas, phis, count) -> int:
    """Write (θ, φ) of e = l1 n1 + l2 n2 at ``count`` if it passes cheirality: 1 written, 0
    rejected, −1 a point at infinity (cheirality cannot tell the solutions apart)."""
    e01 = l1 * n1[0] + l2 * n2[0]
    e10 = l1 * n1[1] + l2 * n2[1]
    e12 = l1 * n1[2] + l2 * n2[2]
    e21 = l1 * n1[3] + l2 * n2[3]
    if e01 * e01 + e21 * e21 < 1e-24:
        return 0
    # eq. (11) without trigonometric calls: cos/sin of θ-φ and φ are entries of e / ρ.
    rho = np.sqrt(e01 * e01 + e21 * e21)
    c1, s1 = e01 / rho, e21 / rho  # cos(θ-φ), sin(θ-φ)
    rho2 = np.sqrt(e10 * e10 + e12 * e12)
    cp, sp = -e10 / rho2, e12 / rho2  # cos φ, sin φ
    ct = c1 * cp - s1 * sp  # cos θ = cos((θ-φ) + φ)
    st = s1 * cp + c1 * sp
    sign = _depth_signs(ct, st, sp, cp, xq, xr)
    if sign == 2:
        return -1
    if sign == 0:
        return 0
    thetas[count] = np.arctan2(st, ct)
    phis[count] = np.arctan2(sign * sp, sign * cp)
    return 1


@njit(cache=True, error_model="numpy")
def solve_planar_2p(xq: np.ndarray, xr: np.ndarray, thetas: np.ndarray, phis: np.ndarray) -> int:
    """Core solver on one sample; writes up to 2 solutions, returns how many.

    Args:
        xq, xr: (2, 3) query / reference rays.
        thetas, phis: (2,) output buffers for yaw θ and translation direction φ (eq. 1).

    Written with scalars and tuples only (no temporary arrays; the stages are inlined): heap
    allocations would dominate the ~100 floating-point operations of a solve.
    """
    ok, r, s = _system_rows(xq, xr)
    if not ok:
        return 0
    ok, n1, n2 = _null_space(r, s)
    if not ok:
        return 0
    ok, v1, v2, mu1, mu2 = _isotropic_basis(n1, n2)
    if not ok:
        return 0
    count = 0
    for sgn in (1.0, -1.0):
        if sgn < 0 and mu1 * mu2 < 1e-9 * (mu1 * mu1 + mu2 * mu2):
            break  # double root
        l1 = v1[0] * mu1 + v2[0] * sgn * mu2
        l2 = v1[1] * mu1 + v2[1] * sgn * mu2
        written = _write_solution(l1, l2, n1, n2, xq, xr, thetas, phis, count)
        if written < 0:
            return 0
        count += written
    return count


@njit(cache=True, error_model="numpy", inline="always")
def planar_pose_into(theta: float, phi: float, R: np.ndarray, t: np.ndarray) -> None:
    """Write ``ref_from_query`` of the paper's (θ, φ) (eq. 1, ρ = 1) into R (3, 3), t (3,)."""
    c, s = np.cos(theta), np.sin(theta)
    sp, cp = np.sin(phi), np.cos(phi)
    R[0, 0], R[0, 1], R[0, 2] = c, 0.0, -s
    R[1, 0], R[1, 1], R[1, 2] = 0.0, 1.0, 0.0
    R[2, 0], R[2, 1], R[2, 2] = s, 0.0, c
    t[0], t[1], t[2] = -(c * sp - s * cp), 0.0, -(s * sp + c * cp)


@njit(cache=True, error_model="numpy")
def _relposes(xq: np.ndarray, xr: np.ndarray, out: np.ndarray) -> int:
    """Validated single call: -1 unless xq, xr are (2, 3) and finite, else the number of poses
    written as ``out[k, :3] = R``, ``out[k, 3] = t`` (eq. 1) into out (2, 4, 3)."""
    if xq.shape[0] != 2 or xq.shape[1] != 3 or xr.shape[0] != 2 or xr.shape[1] != 3:
        return -1
    for i in range(2):
        for j in range(3):
            if not (np.isfinite(xq[i, j]) and np.isfinite(xr[i, j])):
                return -1
    thetas = np.empty(2)
    phis = np.empty(2)
    n = solve_planar_2p(xq, xr, thetas, phis)
    for k in range(n):
        planar_pose_into(thetas[k], phis[k], out[k, :3], out[k, 3])
    return n


@njit(cache=True, error_model="numpy")
def _solve_batch(
    xq: np.ndarray, xr: np.ndarray, thetas: np.ndarray, phis: np.ndarray, counts: np.ndarray
) -> None:
    for i in range(xq.shape[0]):
        counts[i] = solve_planar_2p(xq[i], xr[i], thetas[i], phis[i])


@njit(cache=True, error_model="numpy", parallel=True)
def _solve_batch_parallel(
    xq: np.ndarray, xr: np.ndarray, thetas: np.ndarray, phis: np.ndarray, counts: np.ndarray
) -> None:
    for i in prange(xq.shape[0]):
        counts[i] = solve_planar_2p(xq[i], xr[i], thetas[i], phis[i])


_PARALLEL_MIN_BATCH = 4096  # below this, thread start-up costs more than it saves


def check_rays_or_points(name: str, x: object, shape: tuple) -> np.ndarray:
    """Checked rays of ``shape`` (last axis 3); normalized points with a last axis of 2 (and the
    other axes of ``shape``) get z = 1."""
    arr = check_array(name, x)
    if (
        arr.ndim == len(shape)
        and arr.shape[-1] == 2
        and all(s is None or s == a for s, a in zip(shape[:-1], arr.shape[:-1]))
    ):
        arr = np.concatenate([arr, np.ones(arr.shape[:-1] + (1,))], axis=-1)
    return check_array(name, arr, shape)


def planar_poses(thetas: np.ndarray, phis: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ref_from_query`` of the paper's (θ, φ) (eq. 1, ρ = 1) of shape (M, K): R (M, K, 3, 3),
    t (M, K, 3), NaN where ``valid`` (M, K) is False (the batched solvers' output)."""
    c, s = np.cos(thetas), np.sin(thetas)
    R = np.zeros(thetas.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 2], R[..., 1, 1], R[..., 2, 0], R[..., 2, 2] = c, -s, 1.0, s, c
    d = np.stack([np.sin(phis), np.zeros_like(phis), np.cos(phis)], axis=-1)
    t = -np.einsum("smij,smj->smi", R, d)
    R[~valid] = np.nan
    t[~valid] = np.nan
    return R, t


def relpose_planar_2p(x_query: object, x_ref: object) -> list[Pose]:
    """All planar relative poses ``ref_from_query`` consistent with two matches.

    Args:
        x_query: (2, 3) normalized homogeneous points ``(x, y, 1)`` or bearing vectors in the
            query camera (camera axes x right, y down = gravity, z forward). (2, 2) normalized
            points are accepted and get z = 1.
        x_ref: (2, 3) matching points in the reference camera.

    Returns:
        Up to 2 poses ``ref_from_query`` (``x_ref = R x_query + t``, ``R`` about y, ``‖t‖ = 1``,
        ``t_y = 0``), each placing both points in front of both cameras. Empty for degenerate
        input (repeated matches, zero baseline, points at infinity, no real solution).

    Raises:
        InputError: wrong shape or non-finite values.

    References:
        Paper Sec. IV-A, eq. (1)-(11). Deviation: closed-form isotropic directions of the
        quadratic form instead of intersecting unit circles and filtering (same solutions).

    Example:
        >>> from planarloc.geometry.planar import relpose_from_planar_params
        >>> truth = relpose_from_planar_params(0.2, 0.5)
        >>> X = np.array([[1.0, -0.5, 6.0], [-2.0, 0.8, 9.0]])
        >>> xq = X / X[:, 2:]; Xr = X @ truth.R.T + truth.t; xr = Xr / Xr[:, 2:]
        >>> [round(float(p.t @ truth.t), 6) for p in relpose_planar_2p(xq, xr)]  # doctest: +SKIP
    """
    out = np.empty((2, 4, 3))
    pair = plain_float64_pair(x_query, x_ref, 2)
    n = _relposes(*pair, out) if pair is not None else -1
    if n == -1:  # not a plain float64 array, (2, 2) points, or invalid: convert, or raise the message
        n = _relposes(
            check_rays_or_points("x_query", x_query, (2, 3)),
            check_rays_or_points("x_ref", x_ref, (2, 3)),
            out,
        )
    return Pose._from_buffer(out, n)


def relpose_planar_2p_batch(x_query: object, x_ref: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched :func:`relpose_planar_2p` for M samples, with the contract of the other batched
    solvers.

    Args:
        x_query, x_ref: (M, 2, 3) rays of M two-match samples.

    Large batches run on all cores (numba ``prange``).

    Returns:
        R (M, 2, 3, 3), t (M, 2, 3) of ``ref_from_query`` (unit ``t``) and valid (M, 2) bool;
        valid solutions come first, invalid slots are NaN. Solution ``k`` of sample ``i`` is
        ``relpose_from_planar_params(θ, φ)`` of the paper's parameters.
    """
    xq = check_rays_or_points("x_query", x_query, (None, 2, 3))
    xr = check_rays_or_points("x_ref", x_ref, (None, 2, 3))
    if xq.shape[0] != xr.shape[0]:
        raise InputError(f"x_query and x_ref: different numbers of samples ({xq.shape[0]} vs {xr.shape[0]})")
    return planar_2p_batch_unchecked(xq, xr)


def planar_2p_batch_unchecked(xq: np.ndarray, xr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`relpose_planar_2p_batch` on contiguous float64 (M, 2, 3) arrays, unchecked (the
    RANSAC estimators' entry point)."""
    m = xq.shape[0]
    thetas = np.zeros((m, 2))
    phis = np.zeros((m, 2))
    counts = np.zeros(m, dtype=np.int64)
    (_solve_batch_parallel if m >= _PARALLEL_MIN_BATCH else _solve_batch)(xq, xr, thetas, phis, counts)
    valid = np.arange(2)[None, :] < counts[:, None]
    R, t = planar_poses(thetas, phis, valid)
    return R, t, valid
