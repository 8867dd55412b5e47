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

from planarloc.geometry.epipolar import triangulation_depths
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import check_array


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
    ab0 = a[1] * b[2] - a[2] * b[1]
    ab1 = a[2] * b[0] - a[0] * b[2]
    ab2 = a[0] * b[1] - a[1] * b[0]
    na2 = a[0] ** 2 + a[1] ** 2 + a[2] ** 2
    nb2 = b[0] ** 2 + b[1] ** 2 + b[2] ** 2
    if ab0 * ab0 + ab1 * ab1 + ab2 * ab2 <= 1e-18 * na2 * nb2:
        return np.nan
    ay0 = a[1] * y[2] - a[2] * y[1]
    ay1 = a[2] * y[0] - a[0] * y[2]
    ay2 = a[0] * y[1] - a[1] * y[0]
    by0 = b[1] * y[2] - b[2] * y[1]
    by1 = b[2] * y[0] - b[0] * y[2]
    by2 = b[0] * y[1] - b[1] * y[0]
    den = x2[0] * ay0 + x2[1] * ay1 + x2[2] * ay2
    num = x2[0] * by0 + x2[1] * by1 + x2[2] * by2
    mag = np.sqrt(x2[0] ** 2 + x2[1] ** 2 + x2[2] ** 2) * np.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2)
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
    tv0 = t_unit[1] * v[2] - t_unit[2] * v[1]
    tv1 = t_unit[2] * v[0] - t_unit[0] * v[2]
    tv2 = t_unit[0] * v[1] - t_unit[1] * v[0]
    xv0 = X_ref[1] * v[2] - X_ref[2] * v[1]
    xv1 = X_ref[2] * v[0] - X_ref[0] * v[2]
    xv2 = X_ref[0] * v[1] - X_ref[1] * v[0]
    den = tv0 * tv0 + tv1 * tv1 + tv2 * tv2
    if den <= 1e-12 * (v[0] ** 2 + v[1] ** 2 + v[2] ** 2):
        return np.nan
    return (tv0 * xv0 + tv1 * xv1 + tv2 * xv2) / den


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
    xq = check_array("x_query", x_query, (3,))
    x2 = check_array("x_ref2", x_ref2, (3,))
    t = ref_from_query.t
    n = np.linalg.norm(t)
    if n < 1e-12:
        return []
    t = t / n
    j2_from_j = ref2_cam_from_world @ ref_cam_from_world.inverse()
    a = j2_from_j.R @ t
    y = j2_from_j.R @ ref_from_query.R @ xq
    rho = scale_2p1p(a, j2_from_j.t, y, x2)
    if not np.isfinite(rho):
        return []
    query_from_j = Pose._unchecked(ref_from_query.R.T, -ref_from_query.R.T @ (rho * t))
    pose = query_from_j @ ref_cam_from_world
    j2_from_q = ref2_cam_from_world @ pose.inverse()
    depths = triangulation_depths(j2_from_q.R, j2_from_q.t, xq[None], x2[None])[0]
    return [AbsPose2p1p(pose, float(rho), depths)]
