"""Relative poses from an essential matrix: the four decompositions and the cheirality test.

Convention (see :mod:`planarloc.geometry.epipolar`): ``x_refᵀ E x_query = 0`` with
``E = [t]x R`` for ``ref_from_query = (R, t)``, i.e. ``x_ref ∝ R x_query + t``. An essential
matrix fixes ``t`` only up to scale and sign; decompositions here have ``‖t‖ = 1``.

References:
    Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 9.6.2 (Result 9.19: the four
    solutions ``[UWVᵀ | ±u3]``, ``[UWᵀVᵀ | ±u3]``) and Sec. 9.6.3 (choose the one that puts
    points in front of both cameras). The batched kernel uses instead the SVD-free closed form
    of B. K. P. Horn, "Recovering baseline and orientation from essential matrix", 1990:
    ``R = cof(E) ∓ [t]x E`` for ``‖t‖ = 1`` and ``‖E‖_F² = 2``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planarloc.geometry.epipolar import triangulation_depths
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array, plain_float64_pair

__all__ = [
    "check_correspondence_batch",
    "check_correspondences",
    "solve_correspondences",
    "solve_relpose_batch",
    "motion_from_essential",
    "relposes_from_essential",
]

_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
RANK2_TOL = 1e-10  # sigma_2 / sigma_1 below this: not an essential matrix (rank < 2)


# ---- validation shared by the relative-pose solvers -------------------------------------------


def _check_nonzero_rays(name: str, x: np.ndarray) -> None:
    if np.abs(x).sum(axis=-1).min(initial=np.inf) > 0.0:
        return  # the common case: one reduction
    zero = np.all(x == 0.0, axis=-1)
    if zero.any():
        idx = tuple(int(i) for i in np.argwhere(zero)[0])
        where = idx[0] if len(idx) == 1 else idx
        raise InputError(f"{name}[{where}] is a zero vector; hint: a ray needs a direction, e.g. (x, y, 1)")


def check_correspondences(
    x_query: object, x_ref: object, *, rows: int | None = None, min_rows: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Validate two (N, 3) arrays of matching rays.

    Args:
        x_query, x_ref: (N, 3) rays (normalized homogeneous points or bearings).
        rows: if given, N must equal it.
        min_rows: N must be at least this.

    Returns:
        Both as contiguous float64 arrays.

    Raises:
        InputError: wrong shape, row-count mismatch, NaN/inf, or an all-zero row.
    """
    shape = (rows, 3)
    xq = check_array("x_query", x_query, shape, min_rows=min_rows)
    xr = check_array("x_ref", x_ref, shape, min_rows=min_rows)
    if xq.shape != xr.shape:
        raise InputError(
            f"x_query and x_ref must have the same number of rows, got {xq.shape[0]} and {xr.shape[0]}"
        )
    _check_nonzero_rays("x_query", xq)
    _check_nonzero_rays("x_ref", xr)
    return xq, xr


def solve_correspondences(
    kernel,
    x_query: object,
    x_ref: object,
    out: np.ndarray | None,
    *,
    rows: int | None = None,
    min_rows: int = 1,
) -> tuple[int, np.ndarray, np.ndarray]:
    """Run a validating single-call solver kernel, with :func:`check_correspondences` as fallback.

    ``kernel(xq, xr, out) -> n`` takes two 2-D float64 arrays, validates them itself
    (:func:`planarloc.geometry.validation.rays_invalid`) and returns -1 for invalid input,
    else its result. Plain C-contiguous float64 input goes straight in (one compiled call);
    anything else, and input the kernel rejects, goes through :func:`check_correspondences`,
    which converts it or raises the usual one-line message.

    Returns:
        ``(n, xq, xr)``: the kernel's result and the arrays it ran on.
    """
    pair = plain_float64_pair(x_query, x_ref, 2)
    if pair is not None:
        n = kernel(*pair, out)
        if n != -1:
            return n, *pair
    xq, xr = check_correspondences(x_query, x_ref, rows=rows, min_rows=min_rows)
    n = kernel(xq, xr, out)
    if n == -1:  # pragma: no cover - the kernel and the checks reject the same input
        raise InputError("x_query, x_ref: rejected by the solver kernel although the checks passed")
    return n, xq, xr


def check_correspondence_batch(x_query: object, x_ref: object, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate (M, rows, 3) batches of matching rays; see :func:`check_correspondences`."""
    xq = check_array("x_query", x_query, (None, rows, 3))
    xr = check_array("x_ref", x_ref, (None, rows, 3))
    if xq.shape != xr.shape:
        raise InputError(f"x_query and x_ref must have the same shape, got {xq.shape} and {xr.shape}")
    _check_nonzero_rays("x_query", xq)
    _check_nonzero_rays("x_ref", xr)
    return xq, xr


def _check_essential(E: object) -> np.ndarray:
    E = check_array("E", E)
    if E.ndim < 2 or E.shape[-2:] != (3, 3):
        raise InputError(f"E: expected shape (..., 3, 3), got {E.shape}")
    return E


# ---- the four decompositions -------------------------------------------------------------


def _motion_from_essential(E: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unchecked core of :func:`motion_from_essential`; also returns the singular values."""
    U, S, Vt = np.linalg.svd(E)
    U = U * np.where(np.linalg.det(U) < 0, -1.0, 1.0)[..., None, None]
    Vt = Vt * np.where(np.linalg.det(Vt) < 0, -1.0, 1.0)[..., None, None]
    R1 = U @ _W @ Vt
    R2 = U @ _W.T @ Vt
    t = U[..., :, 2]
    R = np.stack([R1, R1, R2, R2], axis=-3)
    T = np.stack([t, -t, t, -t], axis=-2)
    return R, T, S


def motion_from_essential(E: object) -> tuple[np.ndarray, np.ndarray]:
    """The four ``ref_from_query`` motions ``(R, t)`` with ``E ∝ [t]x R`` (H&Z Result 9.19).

    With ``E = U diag(σ1, σ2, 0) Vᵀ`` (``det U = det V = +1``) and
    ``W = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]`` the solutions are, in this order,
    ``(UWVᵀ, u3), (UWVᵀ, -u3), (UWᵀVᵀ, u3), (UWᵀVᵀ, -u3)``. A matrix with ``σ1 ≠ σ2`` is
    implicitly replaced by its nearest essential matrix ``U diag(1, 1, 0) Vᵀ``.

    Args:
        E: (..., 3, 3) essential matrices, ``x_refᵀ E x_query = 0``; any scale and sign.

    Returns:
        R: (..., 4, 3, 3) rotations (det +1).
        t: (..., 4, 3) unit translations, ``x_ref ∝ R x_query + t``.

    Raises:
        InputError: wrong shape, NaN/inf, or a matrix of rank < 2 (``σ2 ≤ 1e-10 σ1``), for which
        the translation direction is undefined.

    Example:
        >>> from planarloc.geometry.epipolar import essential_from_relpose
        >>> R, t = motion_from_essential(essential_from_relpose(np.eye(3), np.array([1.0, 0, 0])))
        >>> R.shape, t.shape
        ((4, 3, 3), (4, 3))
    """
    E = _check_essential(E)
    try:
        R, T, S = _motion_from_essential(E)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - SVD of finite 3x3 converges
        raise InputError(f"E: SVD failed ({exc})") from None
    bad = ~(S[..., 1] > RANK2_TOL * S[..., 0])
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0]) if bad.ndim else ()
        raise InputError(
            f"E{list(where) if where else ''}: rank < 2 (singular values {S[where] if where else S}); "
            "not an essential matrix, the translation direction is undefined"
        )
    return R, T


def relposes_from_essential(E: object, x_query: object, x_ref: object) -> list[Pose]:
    """Decompositions of ``E`` that put every correspondence in front of both cameras.

    Args:
        E: (3, 3) essential matrix, ``x_refᵀ E x_query = 0``; any scale and sign.
        x_query: (N, 3) query rays (normalized homogeneous points or bearings), N ≥ 1.
        x_ref: (N, 3) matching reference rays.

    Returns:
        ``ref_from_query`` poses (``‖t‖ = 1``) among the four of :func:`motion_from_essential`
        for which **all** N points have positive depth along both rays
        (:func:`planarloc.geometry.epipolar.triangulation_depths`). Usually one pose, or none
        if the points disagree; a point with parallel rays (at infinity, or zero baseline)
        fails the test, so such input gives ``[]``.

    Raises:
        InputError: wrong shapes, NaN/inf, zero rays, or ``E`` of rank < 2.

    References:
        Hartley & Zisserman, 2nd ed., Sec. 9.6.3.
    """
    E = _check_essential(E)
    if E.shape != (3, 3):
        raise InputError(f"E: expected shape (3, 3), got {E.shape}")
    xq, xr = check_correspondences(x_query, x_ref)
    R, T = motion_from_essential(E)
    poses = []
    for k in range(4):
        depths = triangulation_depths(R[k], T[k], xq, xr)
        if np.all(depths > 0.0):
            poses.append(Pose(R[k], T[k]))
    return poses


# ---- numba kernels for the batched solvers ---------------------------------------------------


@njit(cache=True)
def midpoint_depths(R, t, xq, xr, i):
    """Midpoint depths (λ_query, λ_ref) of point i for (R, t), as triangulation_depths.

    Returns (ok, λ_query, λ_ref); ok is False for (near-)parallel rays.
    """
    a0 = R[0, 0] * xq[i, 0] + R[0, 1] * xq[i, 1] + R[0, 2] * xq[i, 2]
    a1 = R[1, 0] * xq[i, 0] + R[1, 1] * xq[i, 1] + R[1, 2] * xq[i, 2]
    a2 = R[2, 0] * xq[i, 0] + R[2, 1] * xq[i, 1] + R[2, 2] * xq[i, 2]
    b0, b1, b2 = xr[i, 0], xr[i, 1], xr[i, 2]
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = b0 * b0 + b1 * b1 + b2 * b2
    ab = a0 * b0 + a1 * b1 + a2 * b2
    at = a0 * t[0] + a1 * t[1] + a2 * t[2]
    bt = b0 * t[0] + b1 * t[1] + b2 * t[2]
    det = aa * bb - ab * ab
    if not det > 1e-12 * aa * bb:
        return False, 0.0, 0.0
    return True, (-at * bb + ab * bt) / det, (aa * bt - ab * at) / det


@njit(cache=True)
def _polar_step(R, out):
    """out = (R + R⁻ᵀ) / 2, one step of the polar iteration (re-orthonormalises a near-rotation)."""
    c00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
    c01 = R[1, 2] * R[2, 0] - R[1, 0] * R[2, 2]
    c02 = R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]
    c10 = R[2, 1] * R[0, 2] - R[2, 2] * R[0, 1]
    c11 = R[2, 2] * R[0, 0] - R[2, 0] * R[0, 2]
    c12 = R[2, 0] * R[0, 1] - R[2, 1] * R[0, 0]
    c20 = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
    c21 = R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]
    c22 = R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]
    h = 0.5 / (R[0, 0] * c00 + R[0, 1] * c01 + R[0, 2] * c02)  # cof(R) / det(R) = R⁻ᵀ
    c = ((c00, c01, c02), (c10, c11, c12), (c20, c21, c22))
    for i in range(3):
        for j in range(3):
            out[i, j] = 0.5 * R[i, j] + h * c[i][j]


@njit(cache=True)
def _orthonormality_error(R) -> float:
    err = 0.0
    for i in range(3):
        for j in range(3):
            d = R[i, 0] * R[j, 0] + R[i, 1] * R[j, 1] + R[i, 2] * R[j, 2] - (1.0 if i == j else 0.0)
            err = max(err, abs(d))
    return err


@njit(cache=True)
def relpose_from_essential_kernel(E, xq, xr, R_out, t_out, work) -> bool:
    """Closed-form decomposition of E (Horn 1990) + cheirality on all rows of xq / xr.

    With ``‖E‖_F² = 2`` and unit ``t`` (orthogonal to every column of ``E = [t]x R``, taken
    as the longest cross product of two columns) the two rotations are
    ``cof(E) ∓ [t]x E``. Writes the first of the four motions ``(R, ±t)`` that passes into
    R_out (3, 3), t_out (3,) (unit). Returns False if none passes or ``E`` is not
    (numerically) essential. ``work`` is a (4, 3, 3) scratch buffer.
    """
    fro = 0.0
    for i in range(3):
        for j in range(3):
            fro += E[i, j] * E[i, j]
    if not (fro > 0.0 and np.isfinite(fro)):
        return False
    En = work[0]
    f = np.sqrt(2.0 / fro)
    for i in range(3):
        for j in range(3):
            En[i, j] = E[i, j] * f
    best = -1.0
    t0 = t1 = t2 = 0.0
    for p in range(3):
        q = (p + 1) % 3
        c0 = En[1, p] * En[2, q] - En[2, p] * En[1, q]
        c1 = En[2, p] * En[0, q] - En[0, p] * En[2, q]
        c2 = En[0, p] * En[1, q] - En[1, p] * En[0, q]
        n2 = c0 * c0 + c1 * c1 + c2 * c2
        if n2 > best:
            best = n2
            t0, t1, t2 = c0, c1, c2
    if not best > 1e-6:  # the largest is >= 1/3 for an essential matrix with ‖E‖_F² = 2
        return False
    inv = 1.0 / np.sqrt(best)
    t = work[3, 0]
    t[0], t[1], t[2] = t0 * inv, t1 * inv, t2 * inv
    Ra = work[1]
    Rb = work[2]
    for i in range(3):
        r1 = (i + 1) % 3
        r2 = (i + 2) % 3
        for j in range(3):
            j1 = (j + 1) % 3
            j2 = (j + 2) % 3
            cof = En[r1, j1] * En[r2, j2] - En[r1, j2] * En[r2, j1]
            # ([t]x En)[i, j] = t[r1] En[r2, j] - t[r2] En[r1, j]
            te = t[r1] * En[r2, j] - t[r2] * En[r1, j]
            Ra[i, j] = cof - te
            Rb[i, j] = cof + te
    # Point 0 selects the candidate: depths are linear in t, so (R, -t) has both depths negated,
    # and of the four motions at most one puts the point in front of both cameras.
    for which in range(2):
        Rc = Ra if which == 0 else Rb
        if not _orthonormality_error(Rc) < 1e-4:
            return False  # E is not an essential matrix
        _polar_step(Rc, R_out)
        _polar_step(R_out, Rc)
        ok, lq, lr = midpoint_depths(Rc, t, xq, xr, np.int64(0))  # typed, not a literal: one signature
        if not ok:
            continue
        if lq > 0.0 and lr > 0.0:
            sign = 1.0
        elif lq < 0.0 and lr < 0.0:
            sign = -1.0
        else:
            continue
        for j in range(3):
            t[j] *= sign
        for i in range(1, xq.shape[0]):
            ok, lq, lr = midpoint_depths(Rc, t, xq, xr, i)
            if not (ok and lq > 0.0 and lr > 0.0):
                return False
        for i in range(3):
            for j in range(3):
                R_out[i, j] = Rc[i, j]
        t_out[0], t_out[1], t_out[2] = t[0], t[1], t[2]
        return True
    return False


@njit(cache=True)
def relpose_batch_kernel(Es, n, xq, xr, R_out, t_out, valid_out) -> int:
    """Decompose ``Es[:n]``; write the poses that pass cheirality packed into the outputs.

    Returns the number of valid poses k (``valid_out[:k]`` set True). Slots past k may hold
    scratch values; callers mask them with ``valid_out``.
    """
    work = np.empty((4, 3, 3))
    k = 0
    for s in range(n):
        if relpose_from_essential_kernel(Es[s], xq, xr, R_out[k], t_out[k], work):
            valid_out[k] = True
            k += 1
    return k


@njit(cache=True)
def relposes_into(Es, n, xq, xr, out) -> int:
    """:func:`relpose_batch_kernel` writing pose k as ``out[k, :3] = R``, ``out[k, 3] = t``.

    ``out`` (≥ n, 4, 3) is the buffer layout of :meth:`planarloc.geometry.pose.Pose._from_buffer`
    (single-call solver APIs). Returns the number of poses written.
    """
    work = np.empty((4, 3, 3))
    R = np.empty((3, 3))
    t = np.empty(3)
    k = 0
    for s in range(n):
        if relpose_from_essential_kernel(Es[s], xq, xr, R, t, work):
            for i in range(3):
                for j in range(3):
                    out[k, i, j] = R[i, j]
                out[k, 3, i] = t[i]
            k += 1
    return k


def relposes_closed_form(Es: np.ndarray, x_query: np.ndarray, x_ref: np.ndarray) -> list[Pose]:
    """Internal, unchecked: poses of several essential matrices passing cheirality on all points.

    Same result as :func:`relposes_from_essential` for each matrix of ``Es`` (K, 3, 3) (at
    most one pose per matrix, as for exact data), computed by the numba kernel of the batched
    solvers: the closed form of Horn (1990) instead of the SVD, and the cheirality test of
    :func:`planarloc.geometry.epipolar.triangulation_depths` re-implemented point by point.
    """
    out = np.empty((max(Es.shape[0], 1), 4, 3))
    return Pose._from_buffer(out, relposes_into(np.ascontiguousarray(Es), Es.shape[0], x_query, x_ref, out))


def solve_relpose_batch(
    kernel, xq: np.ndarray, xr: np.ndarray, max_solutions: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run a batched relative-pose kernel ``kernel(xq, xr, R, t, valid)`` on validated (M, k, 3)
    float64 rays: R (M, max_solutions, 3, 3), t (M, max_solutions, 3), valid (M, max_solutions),
    NaN in the invalid slots (the batch solvers' shared tail; RANSAC calls it on samples of a
    problem validated once, where re-validating each batch cost ~100 µs per call)."""
    M = xq.shape[0]
    R = np.full((M, max_solutions, 3, 3), np.nan)
    t = np.full((M, max_solutions, 3), np.nan)
    valid = np.zeros((M, max_solutions), dtype=np.bool_)
    kernel(xq, xr, R, t, valid)
    R[~valid] = np.nan
    t[~valid] = np.nan
    return R, t, valid
