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

from planarloc.geometry import mat3 as m3
from planarloc.geometry.pose import Pose


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


@njit(cache=True, error_model="numpy")
def _abspose(R, t, R2, t2, Rj, tj, Rj2, tj2, out) -> tuple[bool, float, float, float, bool, float]:
    """The whole of :func:`abspose_2p2p` on the poses' arrays in one compiled call.

    Writes the query ``cam_from_world`` as ``out[0, :3] = R``, ``out[0, 3] = t``; returns
    ``(ok, ρ, ρ₂, rcheck_deg, regularised, sin_parallax)``, ``ok`` False for a zero relative
    translation.
    """
    n1 = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    n2 = np.sqrt(t2[0] * t2[0] + t2[1] * t2[1] + t2[2] * t2[2])
    if n1 < 1e-12 or n2 < 1e-12:
        return False, 0.0, 0.0, 0.0, False, 0.0
    t1u = t / n1
    t2u = t2 / n2
    R12 = m3.mul_t(Rj, Rj2)  # j_from_j2 = ref_cam_from_world ∘ ref2_cam_from_world⁻¹ (T_jj2 of eq. 12)
    t12 = tj - m3.vec(R12, tj2)
    RR2 = m3.mul_t(R, R2)
    tr = 0.0
    for i in range(3):
        tr += R12[i, 0] * RR2[i, 0] + R12[i, 1] * RR2[i, 1] + R12[i, 2] * RR2[i, 2]
    c = (tr - 1.0) / 2.0  # Rcheck, as planarloc.geometry.pose.rotation_error_deg
    rcheck = np.degrees(np.arccos(min(max(c, -1.0), 1.0)))
    t2_in_1 = m3.vec(RR2, t2u)
    rho, rho2, reg = triangulate_scales(t1u, t2_in_1, t12)
    # query_from_world = (R, ρ t̃)⁻¹ ∘ ref_cam_from_world
    Rq = m3.t_mul(R, Rj)
    tq = m3.t_vec(R, tj - rho * t1u)
    for i in range(3):
        for j in range(3):
            out[0, i, j] = Rq[i, j]
        out[0, 3, i] = tq[i]
    c0 = t1u[1] * t2_in_1[2] - t1u[2] * t2_in_1[1]
    c1 = t1u[2] * t2_in_1[0] - t1u[0] * t2_in_1[2]
    c2 = t1u[0] * t2_in_1[1] - t1u[1] * t2_in_1[0]
    return True, rho, rho2, rcheck, reg, np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


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
    out = np.empty((1, 4, 3))
    ok, rho, rho2, rcheck, reg, sin_par = _abspose(
        ref_from_query.R,
        ref_from_query.t,
        ref2_from_query.R,
        ref2_from_query.t,
        ref_cam_from_world.R,
        ref_cam_from_world.t,
        ref2_cam_from_world.R,
        ref2_cam_from_world.t,
        out,
    )
    if not ok:
        raise ValueError("abspose_2p2p: relative translations must be non-zero unit directions")
    return AbsPose2p2p(Pose._from_buffer(out, 1)[0], rho, rho2, rcheck, reg, sin_par)
