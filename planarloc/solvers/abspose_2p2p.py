"""2p2p absolute pose: query pose from two relative poses to references with known poses.

Paper Sec. IV-B, eq. (12)-(15). Given ``ref_from_query`` relative poses ``(R, t̃)`` to
reference ``j`` and ``(R₂, t̃₂)`` to reference ``j₂`` (unit translations, e.g. from two
:func:`~planarloc.solvers.relpose_planar_2p.relpose_planar_2p` solves), and the known
``j_from_j₂ = (R₁₂, t₁₂)`` of the map, eq. (12) gives

* the rotation check (Rcheck) ``e = ∠(R₁₂, R R₂ᵀ)``, and
* the scales ``s = (ρ, ρ₂)`` from ``C s = b`` with ``C = [t̃, -R R₂ᵀ t̃₂]``, ``b = t₁₂``
  (eq. 13), by least squares (eq. 14), regularised with ``+I`` when ``CᵀC`` is singular
  (eq. 15) — which happens when the query is collinear with both reference centres: then
  the result is not a position estimate and ``sin_parallax`` tells so.

The query pose is ``query_from_world = (R, ρ t̃)⁻¹ ∘ cam_from_world_j``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from planarloc.geometry.pose import Pose, rotation_error_deg


@dataclass(frozen=True)
class AbsPose2p2p:
    """Result of :func:`abspose_2p2p`.

    Attributes:
        pose: ``cam_from_world`` of the query (rotation from the pair ``j``).
        rho, rho2: the scales ``ρ``, ``ρ₂`` of eq. (13): distances from the query centre to
            the centres of ``j`` and ``j₂``. Pdcheck requires both > 0.
        rcheck_deg: the rotation-check error of eq. (12) in degrees.
        regularised: True if ``CᵀC`` was singular and eq. (15) was used (degenerate geometry).
        sin_parallax: sine of the angle between the two rays ``t̃`` and ``R R₂ᵀ t̃₂``; near 0
            means the position along the rays is unobservable.
    """

    pose: Pose
    rho: float
    rho2: float
    rcheck_deg: float
    regularised: bool
    sin_parallax: float


@njit(cache=True, error_model="numpy")
def triangulate_scales(
    t1: np.ndarray, t2_in_1: np.ndarray, b: np.ndarray, singular_tol: float = 1e-10
) -> tuple[float, float, bool]:
    """Least-squares ``(ρ, ρ₂)`` of ``[t1, -t2_in_1] s = b`` (eq. 13-15); flags regularisation."""
    c00 = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2]
    c11 = t2_in_1[0] * t2_in_1[0] + t2_in_1[1] * t2_in_1[1] + t2_in_1[2] * t2_in_1[2]
    c01 = -(t1[0] * t2_in_1[0] + t1[1] * t2_in_1[1] + t1[2] * t2_in_1[2])
    g0 = t1[0] * b[0] + t1[1] * b[1] + t1[2] * b[2]
    g1 = -(t2_in_1[0] * b[0] + t2_in_1[1] * b[1] + t2_in_1[2] * b[2])
    det = c00 * c11 - c01 * c01
    regularised = False
    if det <= singular_tol * c00 * c11:
        c00 += 1.0
        c11 += 1.0
        det = c00 * c11 - c01 * c01
        regularised = True
    rho = (c11 * g0 - c01 * g1) / det
    rho2 = (c00 * g1 - c01 * g0) / det
    return rho, rho2, regularised


def abspose_2p2p(
    ref_from_query: Pose,
    ref2_from_query: Pose,
    ref_cam_from_world: Pose,
    ref2_cam_from_world: Pose,
) -> AbsPose2p2p:
    """Query ``cam_from_world`` from two unit-scale relative poses (paper eq. 12-15).

    Args:
        ref_from_query: ``(R, t̃)`` to reference ``j`` (``x_j = R x_query + t̃``, ``‖t̃‖ = 1``).
        ref2_from_query: ``(R₂, t̃₂)`` to reference ``j₂``.
        ref_cam_from_world, ref2_cam_from_world: known map poses of ``j`` and ``j₂``.

    Returns:
        :class:`AbsPose2p2p` with the pose, the scales for Pdcheck and the Rcheck error.
        The solver applies no check itself (contract: the caller decides).

    Raises:
        ValueError: if a relative translation is zero (no direction to triangulate).
    """
    t1 = ref_from_query.t
    t2 = ref2_from_query.t
    n1, n2 = np.linalg.norm(t1), np.linalg.norm(t2)
    if n1 < 1e-12 or n2 < 1e-12:
        raise ValueError("abspose_2p2p: relative translations must be non-zero unit directions")
    t1, t2 = t1 / n1, t2 / n2
    j_from_j2 = ref_cam_from_world @ ref2_cam_from_world.inverse()  # T_jj2 of eq. (12)
    R, R2 = ref_from_query.R, ref2_from_query.R
    rcheck = rotation_error_deg(j_from_j2.R, R @ R2.T)
    t2_in_1 = R @ R2.T @ t2
    rho, rho2, reg = triangulate_scales(t1, t2_in_1, j_from_j2.t)
    query_from_j = Pose._unchecked(R.T, -R.T @ (rho * t1))
    sin_par = float(np.linalg.norm(np.cross(t1, t2_in_1)))
    return AbsPose2p2p(query_from_j @ ref_cam_from_world, float(rho), float(rho2), rcheck, bool(reg), sin_par)
