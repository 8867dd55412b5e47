"""A generic, batched RANSAC/MSAC loop over an estimator protocol.

The loop owns sampling budgets, adaptive termination, local optimisation and statistics;
problem specifics live in the estimator (``planarloc.robust.estimators``). Hypotheses are
generated and scored in batches, so the per-iteration Python overhead is paid once per batch
while the numba kernels do the work.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from planarloc.robust.options import RansacOptions
from planarloc.robust.result import RansacStatistics


class Estimator(Protocol):
    """What the loop needs from a problem.

    ``sample_size`` is the number of data in a minimal sample (for the adaptive iteration
    count), ``num_data`` the number of scored data. ``generate`` draws ``n`` minimal samples
    and returns the hypotheses that passed the solver's checks; ``score`` returns MSAC costs (above ``bound``
    possibly partial lower bounds)
    and inlier counts; ``refine`` improves one model on its inliers (local optimisation);
    ``distinct(R, t, Rb, tb)`` says which of the models ``(R, t)`` (leading dimension n) are
    different solutions from the one model ``(Rb, tb)`` (not the same one found twice), as an
    (n,) bool array; it picks the near-ties that local optimisation also refines.
    """

    sample_size: int
    num_data: int

    def generate(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def score(self, R: np.ndarray, t: np.ndarray, bound: float = ...) -> tuple[np.ndarray, np.ndarray]: ...

    def refine(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def distinct(self, R: np.ndarray, t: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> np.ndarray: ...


@dataclass
class RansacOutput:
    """The best model, and the runner-ups a verifier may want to look at.

    ``alt_R``, ``alt_t``, ``alt_cost``: (k, 3, 3), (k, 3), (k,) the other locally optimised
    models (the near-ties of :func:`_lo_candidates`, and earlier bests) and their MSAC costs,
    within ``ALTERNATIVE_MARGIN_INLIERS · τ²`` of the best cost, lowest first, at most
    ``MAX_ALTERNATIVES``: where one of them refines to a different pose of nearly the same
    cost, the data do not single out one answer. They cost nothing extra to keep.
    ``pool_R``, ``pool_t``: the raw hypotheses whose (possibly partial) cost was within that
    margin of the best raw hypothesis' when scored, for a verifier that wants to look further.
    """

    R: np.ndarray | None
    t: np.ndarray | None
    cost: float
    num_inliers: int
    stats: RansacStatistics
    alt_R: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    alt_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    alt_cost: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pool_R: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    pool_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


# Runner-ups kept for the verifier: MSAC cost within this many inliers' worth (τ² each) of the
# best (planarloc.robust.verification refines them and calls a rival one within half of it).
ALTERNATIVE_MARGIN_INLIERS = 4
MAX_ALTERNATIVES = 8


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Standard bound ``log(1 - p) / log(1 - w^s)`` (inf when w = 0)."""
    w_s = inlier_ratio**sample_size
    if w_s <= 0:
        return math.inf
    if w_s >= 1:
        return 0.0
    return math.log(1.0 - confidence) / math.log(1.0 - w_s)


LO_CANDIDATES = 2
LO_NEAR_TIE = 1.1
#: Adaptive termination also waits for this many hypotheses (solver outputs that passed the
#: checks), within ``max_iterations``. The bound of :func:`required_iterations` assumes that an
#: all-inlier sample yields the true model; a minimal sample of points that nearly lie on one
#: plane (a wall, a facade) yields the essential matrix's planar twin instead, and where most
#: samples are refused by the checks, the few that survive can all be twins: the generated
#: ``offplane`` world, a query 0.5 m below the map, matched to a wall: 100 samples, 5 5-point
#: hypotheses, every one 15° off, locally optimised to a pose 0.54 m / 15.6° off at 2.6 times the
#: cost of the true pose that 2 of the next seed's 6 hypotheses found; the estimate reported
#: 0.10 m of position std (benchmarks/trust.py on a compact map). It costs nothing where samples
#: pass (20 of 100 is a yield most searches exceed).
MIN_HYPOTHESES = 20


def _lo_candidates(estimator: Estimator, R: np.ndarray, t: np.ndarray, cost: np.ndarray, k: int) -> list[int]:
    """The batch's best hypothesis and up to ``LO_CANDIDATES - 1`` near-ties (cost within
    ``LO_NEAR_TIE``) that the estimator calls distinct models (``estimator.distinct``)."""
    chosen = [k]
    order = np.argsort(cost)
    near = order[cost[order] <= LO_NEAR_TIE * cost[k]]
    near = near[near != k]
    # One vectorised ``distinct`` per chosen model: the same model found from several pairs
    # makes most near-ties duplicates, and pairwise calls cost more than the refinement.
    while len(chosen) < LO_CANDIDATES and len(near):
        near = near[estimator.distinct(R[near], t[near], R[chosen[-1]], t[chosen[-1]])]
        if len(near):
            chosen.append(int(near[0]))
            near = near[1:]
    return chosen


def ransac(
    estimator: Estimator,
    options: RansacOptions,
    rng: np.random.Generator,
    stats: RansacStatistics | None = None,
    batch_size: int = 50,
    first_batch: int = 10**9,
) -> RansacOutput:
    """Run MSAC with adaptive termination between ``min_iterations`` and ``max_iterations``
    (and not before :data:`MIN_HYPOTHESES` hypotheses).

    Local optimisation (``estimator.refine``) runs whenever a batch produces a new best model,
    on that model and on up to ``LO_CANDIDATES - 1`` other hypotheses of the batch whose cost is
    within ``LO_NEAR_TIE`` of it: near-ties are where a wrong pose with almost the same support
    (e.g. shifted along a weakly observed direction) can win the raw score but lose after
    refinement.
    """
    stats = stats or RansacStatistics()
    best_R = best_t = None
    best_cost, best_inl = math.inf, 0
    best_raw = math.inf  # best cost of a hypothesis as generated (before local optimisation)
    margin = ALTERNATIVE_MARGIN_INLIERS * options.threshold_px**2
    optimised = []  # (cost, R, t) of every locally optimised model: the runner-ups
    pool_R, pool_t = [], []  # raw hypotheses within the margin (partial costs are lower bounds)
    needed = float(options.max_iterations)
    hypotheses = 0  # of this search (``stats`` may carry counts of earlier ones)
    while stats.iterations < options.max_iterations:
        todo = (
            min(options.min_iterations - stats.iterations, first_batch)
            if stats.iterations < options.min_iterations
            else batch_size
        )
        n = int(min(max(todo, 1), options.max_iterations - stats.iterations))
        t0 = time.perf_counter()
        R, t = estimator.generate(rng, n, stats)
        stats.iterations += n
        t1 = time.perf_counter()
        stats.add_time("hypotheses", t1 - t0)
        hypotheses += len(R)
        if len(R):
            cost, inl = estimator.score(R, t, best_cost)
            stats.scored += len(R)
            k = int(np.argmin(cost))
            best_raw = min(best_raw, float(cost[k]))
            keep = np.flatnonzero(cost <= best_raw + margin)
            pool_R.append(R[keep])
            pool_t.append(t[keep])
            stats.add_time("scoring", time.perf_counter() - t1)
            if cost[k] < best_cost:
                best_R, best_t, best_cost, best_inl = R[k], t[k], float(cost[k]), int(inl[k])
                if options.local_optimization and options.refine:
                    t2 = time.perf_counter()
                    for c in _lo_candidates(estimator, R, t, cost, k):
                        R_lo, t_lo = estimator.refine(R[c], t[c])
                        c_lo, i_lo = estimator.score(R_lo[None], t_lo[None])
                        stats.local_optimizations += 1
                        optimised.append((float(c_lo[0]), R_lo, t_lo))
                        if c_lo[0] < best_cost:
                            best_R, best_t, best_cost, best_inl = R_lo, t_lo, float(c_lo[0]), int(i_lo[0])
                    stats.add_time("local_optimization", time.perf_counter() - t2)
                ratio = best_inl / max(estimator.num_data, 1)
                needed = required_iterations(ratio, estimator.sample_size, options.confidence)
        if (
            stats.iterations >= options.min_iterations
            and stats.iterations >= needed
            and hypotheses >= MIN_HYPOTHESES
        ):
            break
    # Runner-ups: the other locally optimised models within the margin of the best, lowest first.
    alts = sorted(
        (a for a in optimised if a[1] is not best_R and a[0] <= best_cost + margin), key=lambda a: a[0]
    )[:MAX_ALTERNATIVES]
    shape_R = (0, *np.shape(best_R)) if best_R is not None else (0, 3, 3)  # the loop is model-agnostic
    shape_t = (0, *np.shape(best_t)) if best_t is not None else (0, 3)
    alt_R = np.array([a[1] for a in alts]) if alts else np.zeros(shape_R)
    alt_t = np.array([a[2] for a in alts]) if alts else np.zeros(shape_t)
    return RansacOutput(
        best_R,
        best_t,
        best_cost,
        best_inl,
        stats,
        alt_R,
        alt_t,
        np.array([a[0] for a in alts]),
        np.concatenate(pool_R) if pool_R else np.zeros(shape_R),
        np.concatenate(pool_t) if pool_t else np.zeros(shape_t),
    )
