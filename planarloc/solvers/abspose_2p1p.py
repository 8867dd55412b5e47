"""2p1p absolute pose: scale from one match to a second reference (paper Sec. IV-C, eq. 16-18).

With ``ref_from_query = (R, ρ t̃)`` known up to ``ρ`` from pair ``j`` and the known map
transform ``j₂_from_j = (R₂₁, t₂₁)``, eq. (16) gives ``j₂_from_query =
(R₂₁ R, ρ R₂₁ t̃ + t₂₁)``. One match ``(x_q, x_{j₂})`` then satisfies (eq. 18)::

    x_{j₂}ᵀ [ρ a + b]x y = 0,   a = R₂₁ t̃,  b = t₂₁,  y = R₂₁ R x_q

which is linear in ``ρ``: ``ρ = -x_{j₂}·(b × y) / x_{j₂}·(a × y)``. Nothing here assumes the
reference-to-reference transform is planar. The equation is degenerate when
``x_{j₂}·(a × y) = 0`` — in particular when the query centre is collinear with the two
reference centres (then ``a ∥ b`` and the solution is not a position estimate).

:func:`scale_from_point3d` is the structure-aware variant used by the ``tracks`` mode: the
same unknown ``ρ`` fixed by one 2D-3D correspondence instead of a 2D-2D match.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from planarloc.geometry import mat3 as m3
from planarloc.geometry.essential_decomposition import midpoint_depths
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import check_array, plain_float64_pair


@dataclass(frozen=True)
class AbsPose2p1p:
    """Result of :func:`abspose_2p1p`.

    Attributes:
        pose: ``cam_from_world`` of the query.
        rho: scale of eq. (17): distance between the query and reference ``j`` centres;
            Pdcheck requires ``rho > 0``.
        depths: (2,) depths of the third match in the query and in ``j₂`` (cheirality).
    """

    pose: Pose
    rho: float
    depths: np.ndarray


@njit(cache=True, error_model="numpy")
def scale_2p1p(a: np.ndarray, b: np.ndarray, y: np.ndarray, x2: np.ndarray) -> float:
    """``ρ`` of eq. (18); NaN when degenerate.

    Degenerate: ``|x₂·(a×y)|`` ≈ 0 relative to the magnitudes, or ``a ∥ b`` — the query centre
    on the line through both reference centres, where every match yields ``ρ`` placing the
    query on the centre of ``j₂`` regardless of the data.
    """
    ab = m3.cross(a, b)
    if m3.dot(ab, ab) <= 1e-18 * m3.dot(a, a) * m3.dot(b, b):
        return np.nan
    den = m3.dot(x2, m3.cross(a, y))
    num = m3.dot(x2, m3.cross(b, y))
    mag = np.sqrt(m3.dot(x2, x2)) * np.sqrt(m3.dot(y, y))
    if abs(den) <= 1e-12 * mag:
        return np.nan
    return -num / den


@njit(cache=True, error_model="numpy")
def scale_from_point3d(t_unit: np.ndarray, X_ref: np.ndarray, v: np.ndarray) -> float:
    """``ρ`` from one 2D-3D match: least squares of ``(X_ref - ρ t̃) × v = 0``.

    Args:
        t_unit: (3,) ``t̃`` of ``ref_from_query`` (query centre direction in the reference frame).
        X_ref: (3,) the 3D point in reference coordinates.
        v: (3,) the query ray rotated into the reference frame, ``R x_q``.

    Returns:
        ``ρ``, NaN when ``t̃ ∥ v`` (the ray runs along the baseline: no information).
    """
    tv = m3.cross(t_unit, v)
    den = m3.dot(tv, tv)
    if den <= 1e-12 * m3.dot(v, v):
        return np.nan
    return m3.dot(tv, m3.cross(X_ref, v)) / den


@njit(cache=True, error_model="numpy")
def _abspose(R, t, Rj, tj, Rj2, tj2, xq, x2, out) -> tuple[int, float, float, float]:
    """The whole of :func:`abspose_2p1p` on the poses' arrays in one compiled call.

    Returns ``(n, ρ, λ_query, λ_j₂)``: n = -1 unless xq, x2 are (3,) and finite, 0 when
    degenerate, 1 with the query ``cam_from_world`` written as ``out[0, :3] = R``,
    ``out[0, 3] = t``. The depths are NaN for parallel rays (as
    :func:`planarloc.geometry.epipolar.triangulation_depths`).
    """
    if xq.shape[0] != 3 or x2.shape[0] != 3:
        return -1, 0.0, 0.0, 0.0
    for i in range(3):
        if not (np.isfinite(xq[i]) and np.isfinite(x2[i])):
            return -1, 0.0, 0.0, 0.0
    n = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    if n < 1e-12:
        return 0, 0.0, 0.0, 0.0
    tu = t / n
    R21 = m3.mul_t(Rj2, Rj)  # j₂_from_j = ref2_cam_from_world ∘ ref_cam_from_world⁻¹
    t21 = tj2 - m3.vec(R21, tj)
    rho = scale_2p1p(m3.vec(R21, tu), t21, m3.vec(R21, m3.vec(R, xq)), x2)
    if not np.isfinite(rho):
        return 0, 0.0, 0.0, 0.0
    # query_from_world = (R, ρ t̃)⁻¹ ∘ ref_cam_from_world, then j₂_from_query for the depths
    Rq = m3.t_mul(R, Rj)
    tq = m3.t_vec(R, tj - rho * tu)
    R2q = m3.mul_t(Rj2, Rq)
    t2q = tj2 - m3.vec(R2q, tq)
    ok, lq, lr = midpoint_depths(R2q, t2q, xq.reshape((1, 3)), x2.reshape((1, 3)), np.int64(0))
    if not ok:
        lq = lr = np.nan
    for i in range(3):
        for j in range(3):
            out[0, i, j] = Rq[i, j]
        out[0, 3, i] = tq[i]
    return 1, rho, lq, lr


def abspose_2p1p(
    ref_from_query: Pose,
    ref_cam_from_world: Pose,
    ref2_cam_from_world: Pose,
    x_query: object,
    x_ref2: object,
) -> list[AbsPose2p1p]:
    """Query ``cam_from_world`` from a unit-scale relative pose plus one match (eq. 16-18).

    Args:
        ref_from_query: ``(R, t̃)`` to reference ``j``, ``‖t̃‖ = 1``.
        ref_cam_from_world: known map pose of ``j``.
        ref2_cam_from_world: known map pose of ``j₂`` (any rigid transform to ``j``).
        x_query: (3,) normalized homogeneous point in the query.
        x_ref2: (3,) its match in ``j₂``.

    Returns:
        A list with the unique solution, or empty when degenerate (the query centre and
        the two reference centres collinear, or the match on the epipolar plane). The
        scale may be negative: Pdcheck is the caller's (``rho`` and ``depths`` are returned).
    """
    poses = (
        ref_from_query.R,
        ref_from_query.t,
        ref_cam_from_world.R,
        ref_cam_from_world.t,
        ref2_cam_from_world.R,
        ref2_cam_from_world.t,
    )
    out = np.empty((1, 4, 3))
    n = -1
    pair = plain_float64_pair(x_query, x_ref2, 1)
    if pair is not None:
        n, rho, lq, lr = _abspose(*poses, *pair, out)
    if n == -1:  # not a plain float64 array, or invalid: convert, or raise the usual message
        xq = check_array("x_query", x_query, (3,))
        n, rho, lq, lr = _abspose(*poses, xq, check_array("x_ref2", x_ref2, (3,)), out)
    if n <= 0:
        return []
    return [AbsPose2p1p(Pose._from_buffer(out, 1)[0], rho, np.array([lq, lr]))]
