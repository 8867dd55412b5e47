"""Minimal-sample drawing for multi-pair problems (numba; randomness from a numpy Generator).

Pairs are chosen in proportion to their numbers of matches; matches within a pair are
distinct. The uniform variates come from the caller's seeded ``numpy.random.Generator``
so results are reproducible and independent of numba's own generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit


@njit(cache=True)
def _pick_weighted(u: float, weights: np.ndarray, exclude: int | np.integer) -> int:
    total = 0.0
    for p in range(weights.shape[0]):
        if p != exclude:
            total += weights[p]
    target = u * total
    acc = 0.0
    last = -1
    for p in range(weights.shape[0]):
        if p == exclude or weights[p] <= 0:
            continue
        acc += weights[p]
        last = p
        if target < acc:
            return p
    return last


@njit(cache=True)
def _distinct(u: np.ndarray, n: int, out: np.ndarray, start: int | np.integer, m: int, base: int) -> None:
    """Write m distinct integers from [0, n) (plus base) into out[start:start+m]."""
    chosen = np.empty(m, dtype=np.int64)
    for i in range(m):
        r = int(u[i] * (n - i))
        if r >= n - i:
            r = n - i - 1
        # Shift past previously chosen values (kept sorted) to stay uniform without replacement.
        for c in range(i):
            if r >= chosen[c]:
                r += 1
        pos = i
        while pos > 0 and chosen[pos - 1] > r:
            chosen[pos] = chosen[pos - 1]
            pos -= 1
        chosen[pos] = r
    for i in range(m):
        out[start + i] = base + chosen[i]
    # Randomise order is not needed: solvers are symmetric in their inputs.


@njit(cache=True)
def draw_pair_samples(
    u: np.ndarray,
    offsets: np.ndarray,
    m_first: int,
    m_second: int,
    samples: np.ndarray,
    pj: np.ndarray,
    pk: np.ndarray,
) -> None:
    """Draw S samples of ``m_first`` matches from a pair j and ``m_second`` from a pair k ≠ j.

    Args:
        u: (S, 2 + m_first + m_second) uniform variates in [0, 1).
        offsets: (P + 1,) row offsets of the pairs.
        samples: (S, m_first + m_second) output rows (global match rows).
        pj, pk: (S,) output pair indices.
    """
    P = offsets.shape[0] - 1
    w1 = np.zeros(P)
    w2 = np.zeros(P)
    for p in range(P):
        n = offsets[p + 1] - offsets[p]
        if n >= m_first:
            w1[p] = n
        if n >= m_second:
            w2[p] = n
    for s in range(u.shape[0]):
        j = _pick_weighted(u[s, 0], w1, np.int64(-1))  # typed, not a literal: one compiled signature
        k = _pick_weighted(u[s, 1], w2, j)
        pj[s] = j
        pk[s] = k
        _distinct(
            u[s, 2 : 2 + m_first], offsets[j + 1] - offsets[j], samples[s], np.int64(0), m_first, offsets[j]
        )
        if m_second > 0 and k >= 0:
            _distinct(
                u[s, 2 + m_first :], offsets[k + 1] - offsets[k], samples[s], m_first, m_second, offsets[k]
            )


def eligible_pairs(counts: Sequence[int] | np.ndarray, m_first: int, m_second: int) -> bool:
    """True if some pair has ``m_first`` matches and a different one ``m_second``."""
    # Plain Python on a few pair counts: called per query and family, where numpy's per-call
    # overhead was most of the cost.
    first = [j for j, c in enumerate(counts) if c >= m_first]
    second = [k for k, c in enumerate(counts) if c >= m_second]
    return bool(first) and bool(second) and not (len(first) == 1 and second == first)


@njit(cache=True)
def draw_within_pairs(
    u: np.ndarray, offsets: np.ndarray, sample_pair: np.ndarray, m: int, samples: np.ndarray
) -> None:
    """Draw ``m`` distinct matches of pair ``sample_pair[s]`` for every sample ``s``.

    Args:
        u: (S, m) uniform variates; samples: (S, m) output global match rows.
    """
    for s in range(u.shape[0]):
        p = sample_pair[s]
        _distinct(u[s], offsets[p + 1] - offsets[p], samples[s], np.int64(0), m, offsets[p])
