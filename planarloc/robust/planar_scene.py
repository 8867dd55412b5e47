"""Does a reference's support show a distant plane? The homography test of two-view geometry.

When the matched points of a query-reference pair lie on one plane, or so far away that the
translation hardly moves them, one homography explains the matches (Hartley & Zisserman,
*Multiple View Geometry*, 2nd ed., Sec. 13.1 and 11.9.2): the epipolar geometry then leaves
rotation and translation of that pair entangled — a continuum of relative poses fits within
the noise — and the linearised covariance of a pose resting on such pairs is far too small
(a generated facade 20 m away seen by four map images 2 m apart: poses 0.6 m / 2.5° off with
a position std of 0.13 m). COLMAP's two-view geometry makes the same test
(``TwoViewGeometry::PLANAR_OR_PANORAMIC`` when the homography inliers exceed 80 % of the
epipolar ones). Not in the paper.

The homography is fitted to the pair's epipolar inliers by the normalised DLT (Hartley &
Zisserman Alg. 4.2), refitted twice on its own inliers; its smallest right singular vector is
found by inverse iteration on the 9x9 normal matrix (the repository avoids numba's LAPACK
bindings, which cost tens of seconds of compile time).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.numerics.cholesky import solve_spd
from planarloc.robust.problem import ProblemArrays

PLANAR_INLIER_RATIO = 0.9
"""A pair whose epipolar inliers are at least this share homography inliers is a planar scene."""

FAR_RATIO = 3.0
"""... and a distant one when its median depth from the query exceeds this many times the spread
of the supporting map images' centres. A plane seen by map images that stand close together
relative to it fixes neither rotation nor translation of the query alone (generated facades
20-30 m away, map images within 2-5 m: ratios 3.1-10; rendered offices, whose posters are planar
too, 0.9-3.0, and their poses are right: they are seen through hundreds of inliers, see
:data:`FEW_INLIERS`)."""

FEW_INLIERS = 100
"""... seen through fewer inliers than this. With hundreds of matches even a small relief of the
plane pins the epipolar geometry (rendered offices through two map images 0.5 m apart, a wall 2 m
away, 270-680 inliers: poses 1-5 cm off with honest stds); with a few dozen it does not."""

_REFITS = 2


@njit(cache=True, error_model="numpy")
def _normalizer(x: np.ndarray, rows: np.ndarray, keep: np.ndarray) -> tuple[float, float, float]:
    """Centroid and scale (mean distance √2) of the kept points (Hartley's normalisation)."""
    mx = my = 0.0
    n = 0
    for i in range(rows.shape[0]):
        if keep[i]:
            mx += x[rows[i], 0] / x[rows[i], 2]
            my += x[rows[i], 1] / x[rows[i], 2]
            n += 1
    mx /= max(n, 1)
    my /= max(n, 1)
    d = 0.0
    for i in range(rows.shape[0]):
        if keep[i]:
            d += np.sqrt(
                (x[rows[i], 0] / x[rows[i], 2] - mx) ** 2 + (x[rows[i], 1] / x[rows[i], 2] - my) ** 2
            )
    d /= max(n, 1)
    return mx, my, np.sqrt(2.0) / max(d, 1e-12)


@njit(cache=True, error_model="numpy")
def _fit(xq: np.ndarray, xr: np.ndarray, rows: np.ndarray, keep: np.ndarray, H: np.ndarray) -> bool:
    """Normalised DLT of ``x_r ∝ H x_q`` on the kept rows; H (3, 3) written in place."""
    qx, qy, qs = _normalizer(xq, rows, keep)
    rx, ry, rs = _normalizer(xr, rows, keep)
    A = np.zeros((9, 9))
    row = np.empty(9)
    for i in range(rows.shape[0]):
        if not keep[i]:
            continue
        k = rows[i]
        u, v = (xq[k, 0] / xq[k, 2] - qx) * qs, (xq[k, 1] / xq[k, 2] - qy) * qs
        up, vp = (xr[k, 0] / xr[k, 2] - rx) * rs, (xr[k, 1] / xr[k, 2] - ry) * rs
        for eq in range(2):
            if eq == 0:
                row[0], row[1], row[2] = -u, -v, -1.0
                row[3], row[4], row[5] = 0.0, 0.0, 0.0
                row[6], row[7], row[8] = up * u, up * v, up
            else:
                row[0], row[1], row[2] = 0.0, 0.0, 0.0
                row[3], row[4], row[5] = -u, -v, -1.0
                row[6], row[7], row[8] = vp * u, vp * v, vp
            for a in range(9):
                for b in range(9):
                    A[a, b] += row[a] * row[b]
    # Smallest eigenvector of AᵀA by inverse iteration with a small shift.
    scale = 0.0
    for a in range(9):
        scale = max(scale, A[a, a])
    if not scale > 0.0:
        return False
    S = A.copy()
    for a in range(9):
        S[a, a] += 1e-10 * scale
    h = np.ones(9) / 3.0
    nxt = np.empty(9)
    for _ in range(30):
        if not solve_spd(S, h, nxt):
            return False
        norm = np.sqrt(np.sum(nxt * nxt))
        if not norm > 0.0:
            return False
        h = nxt / norm
    Hn = h.reshape(3, 3)
    # Undo the normalisations: H = T_r⁻¹ Hn T_q.
    Tq = np.array([[qs, 0.0, -qs * qx], [0.0, qs, -qs * qy], [0.0, 0.0, 1.0]])
    Tr_inv = np.array([[1.0 / rs, 0.0, rx], [0.0, 1.0 / rs, ry], [0.0, 0.0, 1.0]])
    Hw = Tr_inv @ Hn @ Tq
    for a in range(3):  # element-wise: a slice assignment compiles numba's shape-error path (1-3 s)
        for b in range(3):
            H[a, b] = Hw[a, b]
    return True


@njit(cache=True, error_model="numpy")
def homography_inlier_ratio(
    xq: np.ndarray, xr: np.ndarray, rows: np.ndarray, f_ref: np.ndarray, threshold_px: float
) -> float:
    """Share of the matches ``rows`` that one homography maps within ``threshold_px``.

    Args:
        xq, xr: (N, 3) normalized homogeneous query and reference points.
        rows: (K,) the pair's (epipolar) inliers, K ≥ 8 for a meaningful answer (else 0).
        f_ref: (2,) the reference's focal lengths: errors are measured in its pixels.
        threshold_px: transfer error tolerance (both keypoints are noisy: about twice the
            epipolar threshold).

    Returns:
        the inlier share of the best of the fit and its refits on their own inliers.
    """
    n = rows.shape[0]
    if n < 8:
        return 0.0
    keep = np.ones(n, dtype=np.bool_)
    H = np.empty((3, 3))
    best = 0.0
    th2 = threshold_px * threshold_px
    for _ in range(_REFITS + 1):
        if not _fit(xq, xr, rows, keep, H):
            break
        count = 0
        for i in range(n):
            k = rows[i]
            a = H[0, 0] * xq[k, 0] + H[0, 1] * xq[k, 1] + H[0, 2] * xq[k, 2]
            b = H[1, 0] * xq[k, 0] + H[1, 1] * xq[k, 1] + H[1, 2] * xq[k, 2]
            c = H[2, 0] * xq[k, 0] + H[2, 1] * xq[k, 1] + H[2, 2] * xq[k, 2]
            if c == 0.0:
                keep[i] = False
                continue
            du = (a / c - xr[k, 0] / xr[k, 2]) * f_ref[0]
            dv = (b / c - xr[k, 1] / xr[k, 2]) * f_ref[1]
            keep[i] = du * du + dv * dv <= th2
            count += keep[i]
        best = max(best, count / n)
        if count < 8:
            break
    return best


@njit(cache=True, error_model="numpy")
def median_depth(R: np.ndarray, t: np.ndarray, prob: ProblemArrays, rows: np.ndarray, k: int) -> float:
    """Median distance from the query centre of the midpoint triangulations of the matches
    ``rows`` of pair ``k`` (query ``cam_from_world = (R, t)``); NaN if none triangulates in front
    of the query."""
    xq, xr = prob.xq, prob.xr
    R_rq = m3.mul_t(prob.ref_R[k], R)
    t_rq = prob.ref_t[k] - m3.vec(R_rq, t)
    depth = np.empty(rows.shape[0])
    k = 0
    for n in range(rows.shape[0]):
        i = rows[n]
        a = m3.vec(R_rq, xq[i])
        b = xr[i]
        aa, bb, ab = m3.dot(a, a), m3.dot(b, b), m3.dot(a, b)
        det = aa * bb - ab * ab
        if det <= 1e-12 * aa * bb:
            continue
        lq = (-m3.dot(a, t_rq) * bb + ab * m3.dot(b, t_rq)) / det
        if lq > 0:
            depth[k] = lq * np.sqrt(m3.dot(xq[i], xq[i]))
            k += 1
    return np.median(depth[:k]) if k else np.nan


def distant_planar_pairs(
    problem,
    R: np.ndarray,
    t: np.ndarray,
    in2d: np.ndarray,
    pairs: np.ndarray,
    threshold_px: float,
    any_plane: bool = False,
) -> np.ndarray:
    """(len(pairs),) bool: which of the given pairs see a distant plane through few inliers from
    the pose ``(R, t)``.

    A pair qualifies when it has fewer than :data:`FEW_INLIERS` inliers, one homography explains
    them (share ≥ :data:`PLANAR_INLIER_RATIO`, transfer error within ``threshold_px``) and their
    median depth from the query (:func:`median_depth`) exceeds :data:`FAR_RATIO` times the
    spread (largest distance) of the centres of ``pairs``. ``any_plane``: every pair whose
    inliers one homography explains, near or far, however many: the pose came from the 8-point
    algorithm, which is degenerate on a plane (Hartley & Zisserman Sec. 11.9.2: the epipolar
    geometry of points on a plane is not unique; generated offices seen 0.8 m from the map images
    gave 8-point poses 15-21° off with a 0.1 m position std)."""
    out = np.zeros(len(pairs), dtype=np.bool_)
    _distant_planar_kernel(
        np.ascontiguousarray(R, dtype=float),
        np.ascontiguousarray(t, dtype=float),
        problem.arrays,
        np.ascontiguousarray(in2d),
        np.asarray(pairs, dtype=np.int64),
        float(threshold_px),
        bool(any_plane),
        out,
    )
    return out


@njit(cache=True, error_model="numpy")
def _distant_planar_kernel(
    R: np.ndarray,
    t: np.ndarray,
    prob: ProblemArrays,
    in2d: np.ndarray,
    pairs: np.ndarray,
    threshold_px: float,
    any_plane: bool,
    out: np.ndarray,
) -> None:
    """The loop of :func:`distant_planar_pairs` over ``pairs`` (K,) into ``out`` (K,) bool, in one
    compiled call (the cheap tests first: few inliers, far; then the homography)."""
    xq, xr, offsets, ref_R, ref_t, f_ref = prob.xq, prob.xr, prob.offsets, prob.ref_R, prob.ref_t, prob.f_ref
    K = pairs.shape[0]
    spread = 0.0  # largest distance between the centres of the pairs' map images
    for a in range(K):
        ca = -(ref_R[pairs[a]].T @ ref_t[pairs[a]])
        for b in range(a + 1, K):
            cb = -(ref_R[pairs[b]].T @ ref_t[pairs[b]])
            spread = max(spread, np.sqrt(np.sum((ca - cb) ** 2)))
    for i in range(K):
        k = pairs[i]
        lo, hi = offsets[k], offsets[k + 1]
        n = 0
        for j in range(lo, hi):
            n += in2d[j]
        rows = np.empty(n, dtype=np.int64)
        n = 0
        for j in range(lo, hi):
            if in2d[j]:
                rows[n] = j
                n += 1
        if not any_plane:
            if n >= FEW_INLIERS or not median_depth(R, t, prob, rows, k) > FAR_RATIO * spread:
                continue
        out[i] = homography_inlier_ratio(xq, xr, rows, f_ref[k], threshold_px) >= PLANAR_INLIER_RATIO
