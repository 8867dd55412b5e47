"""The Python functions of both five-point solvers, written once: checked calls and docstrings.

Nistér's (:mod:`planarloc.solvers.relpose_5p_nister`) and Stewénius' solver
(:mod:`planarloc.solvers.relpose_5p_stewenius`) have the same public contract; they differ in
their compiled entry points (the drivers of :mod:`planarloc.solvers._five_point` bound to each
solver's essentials kernel) and their references. Each solver module puts its entry points in a
:class:`FivePointCalls` and binds the four functions of :meth:`FivePointCalls.public_functions`
to its public names; their docstrings are the templates here filled in with the solver's name
and references.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from planarloc.geometry.essential_decomposition import (
    check_correspondence_batch,
    solve_correspondences,
    solve_relpose_batch,
)
from planarloc.geometry.pose import Pose
from planarloc.solvers._five_point import MAX_SOLUTIONS

# Templates of the public docstrings; fields: {name} (the function), {batch} (the name of the
# batch function), {solver} (e.g. "Nistér's five-point"), {citation} (e.g. "Nistér 2004"),
# {references} (no final full stop).
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


UNCHECKED_DOC = """:func:`{batch}` on validated contiguous float64 (M, 5, 3) rays (the RANSAC
    estimators' entry point: their problem is validated once)."""


# The types of the four public functions (a Protocol, for the keyword-only ``parallel``).
class Essentials(Protocol):
    def __call__(self, x_query: object, x_ref: object) -> list[np.ndarray]: ...


class Relposes(Protocol):
    def __call__(self, x_query: object, x_ref: object) -> list[Pose]: ...


class Batch(Protocol):
    def __call__(
        self, x_query: object, x_ref: object, *, parallel: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


class BatchUnchecked(Protocol):
    def __call__(
        self, xq: np.ndarray, xr: np.ndarray, *, parallel: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


class FivePointFunctions(NamedTuple):
    """A solver's public functions, in the order its module binds them."""

    essentials: Essentials
    relposes: Relposes
    batch: Batch
    batch_unchecked: BatchUnchecked


def _publish(fn: Callable[..., object], module: str, name: str, doc: str) -> None:
    """Give ``fn`` the identity of the public function ``module.name`` (``help()``, pickling,
    cross-references) and its docstring."""
    fn.__module__, fn.__name__, fn.__qualname__, fn.__doc__ = module, name, name, doc


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

    def public_functions(
        self, module: str, tag: str, *, solver: str, citation: str, references: str
    ) -> FivePointFunctions:
        """The four public functions of the solver module ``module``: ``essentials_5p_{tag}``,
        ``relpose_5p_{tag}``, ``relpose_5p_{tag}_batch`` and ``relpose_5p_{tag}_batch_unchecked``
        (``tag`` e.g. ``"nister"``), documented by the templates above with the other fields."""
        essentials_kernel, relposes_kernel = self.essentials, self.relposes
        batch_kernel, batch_parallel_kernel = self.batch, self.batch_parallel

        def essentials(x_query: object, x_ref: object) -> list[np.ndarray]:
            Es = np.empty((MAX_SOLUTIONS, 3, 3))
            n, _, _ = solve_correspondences(essentials_kernel, x_query, x_ref, Es, rows=5)
            return list(Es[:n])

        def relposes(x_query: object, x_ref: object) -> list[Pose]:
            out = np.empty((MAX_SOLUTIONS, 4, 3))
            return Pose._from_buffer(
                out, solve_correspondences(relposes_kernel, x_query, x_ref, out, min_rows=5)[0]
            )

        def batch(
            x_query: object, x_ref: object, *, parallel: bool = False
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return batch_unchecked(*check_correspondence_batch(x_query, x_ref, 5), parallel=parallel)

        def batch_unchecked(
            xq: np.ndarray, xr: np.ndarray, *, parallel: bool = False
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            kernel = batch_parallel_kernel if parallel else batch_kernel
            return solve_relpose_batch(kernel, xq, xr, MAX_SOLUTIONS)

        fields = {"solver": solver, "citation": citation, "references": references}
        batch_name = f"relpose_5p_{tag}_batch"
        for fn, name, template in (
            (essentials, f"essentials_5p_{tag}", ESSENTIALS_DOC),
            (relposes, f"relpose_5p_{tag}", RELPOSES_DOC),
            (batch, batch_name, BATCH_DOC),
            (batch_unchecked, f"{batch_name}_unchecked", UNCHECKED_DOC),
        ):
            _publish(fn, module, name, template.format(name=name, batch=batch_name, **fields))
        return FivePointFunctions(essentials, relposes, batch, batch_unchecked)
