"""The Python functions of both five-point solvers, written once: checked calls and docstrings.

Nistér's (:mod:`planarloc.solvers.relpose_5p_nister`) and Stewénius' solver
(:mod:`planarloc.solvers.relpose_5p_stewenius`) have the same public contract; they differ in
their compiled entry points (the drivers of :mod:`planarloc.solvers._five_point` bound to each
solver's essentials kernel) and their references. Each solver module defines its public
functions on :class:`FivePointCalls` bound to its entry points, and :func:`five_point_doc` fills
in their docstrings from the templates here with the solver's name and references.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from planarloc.geometry.essential_decomposition import (
    check_correspondence_batch,
    solve_correspondences,
    solve_relpose_batch,
)
from planarloc.geometry.pose import Pose
from planarloc.solvers._five_point import MAX_SOLUTIONS

_F = TypeVar("_F", bound=Callable[..., object])

# Templates of the public docstrings; fields: {name} (the function), {solver} (e.g. "Nistér's
# five-point"), {citation} (e.g. "Nistér 2004"), {references} (no final full stop).
ESSENTIALS_DOC = """All real essential matrices consistent with five correspondences ({citation}).

    Args:
        x_query: (5, 3) rays of the query camera: normalized homogeneous points ``(x, y, 1)``
            or bearing vectors (any non-zero length, any direction).
        x_ref: (5, 3) rays of the reference camera, row ``i`` matching ``x_query[i]``.

    Returns:
        Up to 10 (3, 3) essential matrices with ``x_refᵀ E x_query = 0``, unit Frobenius norm,
        sign arbitrary. No cheirality filtering. Empty for a degenerate sample (repeated points,
        pure rotation, all points on one epipolar plane; see the module docstring).

    Raises:
        InputError: wrong shape, NaN/inf, or a zero-length ray.

    References:
        {references}.

    Example:
        >>> Es = {name}(x_query, x_ref)   # doctest: +SKIP
    """

RELPOSES_DOC = """All relative poses from five (or more) correspondences, {solver} method.

    Args:
        x_query: (N ≥ 5, 3) rays of the query camera (normalized homogeneous points or
            bearings). Only the **first five** rows enter the minimal solve.
        x_ref: (N, 3) matching rays of the reference camera.

    Returns:
        ``ref_from_query`` poses (``x_ref ∝ R x_query + t``, ``‖t‖ = 1``), one for each real
        essential matrix whose decomposition puts **all N** points in front of both cameras
        (the midpoint test of :func:`planarloc.geometry.epipolar.triangulation_depths`; the
        pose from the closed form of the batched kernel, equal to
        :func:`~planarloc.geometry.essential_decomposition.relposes_from_essential`).
        Passing extra points thus prunes the up to 10 minimal solutions. Empty for degenerate
        input: repeated points, pure rotation, points at infinity (parallel rays), all points on
        one epipolar plane.

    Raises:
        InputError: wrong shape, fewer than 5 rows, NaN/inf, or a zero-length ray.

    References:
        {references}.
    """

BATCH_DOC = """{solver} solver on M samples at once (for RANSAC).

    Args:
        x_query: (M, 5, 3) query rays (normalized homogeneous points or bearings).
        x_ref: (M, 5, 3) matching reference rays.
        parallel: spread the samples over numba's threads (``numba.set_num_threads``). Off by
            default: the OpenMP/TBB thread pools are not fork-safe, so a process that later
            forks workers (``multiprocessing`` on Linux) must not have used them.

    Returns:
        R: (M, 10, 3, 3) rotations ``ref_from_query``; NaN where not valid.
        t: (M, 10, 3) unit translations; NaN where not valid.
        valid: (M, 10) bool; True for a real solution whose pose puts all five sample points in
        front of both cameras. Valid solutions are packed first: ``valid[m, :k]``.

    Raises:
        InputError: wrong shape, NaN/inf, or a zero-length ray. Degenerate samples raise
        nothing; their rows of ``valid`` are all False.

    References:
        {references}. The pose comes from the closed-form decomposition
        ``R = cof(E) ∓ [t]x E`` (Horn 1990) of
        :func:`planarloc.geometry.essential_decomposition.relpose_from_essential_kernel`, as in
        the single call.
    """


def five_point_doc(template: str, **fields: str) -> Callable[[_F], _F]:
    """Decorator: the function's docstring is ``template`` (one of the ``*_DOC`` above) filled in
    with ``fields`` and the function's own ``name``."""

    def document(fn: _F) -> _F:
        fn.__doc__ = template.format(name=getattr(fn, "__name__", ""), **fields)
        return fn

    return document


@dataclass(frozen=True)
class FivePointCalls:
    """A solver's compiled entry points (its module binds the drivers of
    :mod:`planarloc.solvers._five_point` to its essentials kernel) and the public calls on them.

    ``essentials(xq, xr, E_out)``, ``relposes(xq, xr, out)``: validating single calls (-1 for
    invalid input); ``batch(xq, xr, R, t, valid)`` and its ``prange`` twin ``batch_parallel``.
    """

    essentials: Callable[..., int]
    relposes: Callable[..., int]
    batch: Callable[..., None]
    batch_parallel: Callable[..., None]

    def essentials_of(self, x_query: object, x_ref: object) -> list[np.ndarray]:
        """The essential matrices of five matches (:data:`ESSENTIALS_DOC`)."""
        Es = np.empty((MAX_SOLUTIONS, 3, 3))
        n, _, _ = solve_correspondences(self.essentials, x_query, x_ref, Es, rows=5)
        return list(Es[:n])

    def relposes_of(self, x_query: object, x_ref: object) -> list[Pose]:
        """The poses of N ≥ 5 matches (:data:`RELPOSES_DOC`)."""
        out = np.empty((MAX_SOLUTIONS, 4, 3))
        return Pose._from_buffer(
            out, solve_correspondences(self.relposes, x_query, x_ref, out, min_rows=5)[0]
        )

    def batch_of(
        self, x_query: object, x_ref: object, parallel: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The batch of (M, 5, 3) samples, validated (:data:`BATCH_DOC`)."""
        return self.batch_unchecked(*check_correspondence_batch(x_query, x_ref, 5), parallel)

    def batch_unchecked(
        self, xq: np.ndarray, xr: np.ndarray, parallel: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`batch_of` on validated contiguous float64 (M, 5, 3) rays."""
        return solve_relpose_batch(self.batch_parallel if parallel else self.batch, xq, xr, MAX_SOLUTIONS)
