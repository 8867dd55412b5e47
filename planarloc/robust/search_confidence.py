"""How sure a finished search can be that no pose with more support than its own went unsampled.

RANSAC's stopping rule draws samples until an all-inlier sample of the best pose's support would
have been drawn with the chosen confidence (:func:`planarloc.robust.ransac.required_iterations`).
A search that stops on its budget first (``max_iterations``, a fixed ``--iterations``) may have
missed a pose that more matches support, and then every check of its pose compares it only with
the poses the search did find: its restarts, runner-ups and jackknife agree, and the pose is
wrong far beyond its std (the scenes of ``benchmarks/robustness.py --protocol hard`` with bare
``2p1p`` at 5, 10 and 20 fixed samples: 22 of 724, 10 of 816 and 4 of 860 successes up to 7.2 m
off with stds of 0.09-0.26 m; none of 529 at the protocol's 100).

The probability that a pose with at least the found pose's inliers would have given no good
sample in the samples drawn bounds what was missed: more support means a larger chance per
sample. Every search of an estimate (the planar one, the 6DoF one, a short check) could have
found such a pose, so the estimate's chance is the product of theirs, each with its own samples.
Each family's sampling gives it its own form, all functions of the found inliers per map image
(:func:`inlier_ratios`) and the samples drawn:

* one draw per sample (:func:`missed_by_draws`): ``(1 - p)^n``, with ``p`` the chance of a good
  sample, e.g. ``Σ_j w_j r_j²`` for 2p1p's two matches of one map image j drawn with weight
  ``w_j`` (the consensus scale needs no third draw; :func:`pair_sample_chance`);
* two-stage relative poses (2p2p, 5p5p, 8p8p, paper Sec. IV-B; :func:`missed_by_pairs`): ``n``
  samples of ``m`` matches in every map image, and a pose needs good samples in two of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np

#: A success needs the chance that its searches all missed a better-supported pose (the product
#: over the estimate's searches, each drawing its own samples) at most this. The hard protocol's
#: 1,000 scenes at 5, 10 and 20 fixed samples: 22 / 10 / 4 broken promises of bare ``2p1p`` and
#: 21 / 10 / 4 of ``auto`` before, none with it (bare ``2p1p`` also at 0.01 and 0.1); at 100
#: samples and with the default adaptive budget it refuses nothing there (BENCHMARKS.md, "A
#: search's own confidence").
MAX_MISS_PROBABILITY = 0.05

# Samples per map image of the short 6DoF search that checks a planar pose: at most this many,
# fewer where the planar pose's inlier ratio says a clean 5-point sample comes sooner
# (:func:`rival_check_samples`).
RIVAL_CHECK_ITERATIONS = 10
RIVAL_CHECK_CONFIDENCE = 0.9  # chance of one all-inlier sample per map image the budget aims at

#: A cross-checked planar pose on fewer inliers than this gets a second, independent search of
#: its family (its own samples, the full budget): the bound above assumes an all-inlier sample
#: yields the true pose, and on so little support it may not. The hard protocol (3 x 20 matches,
#: 1.5 px, 60 % outliers, seed 79) had a success 0.53 m off with a 0.15 m std on 19 inliers: the
#: truth's basin was 15 px² cheaper, and none of the search's 8 hypotheses lay in it. The better
#: of the two searches is the answer, and one elsewhere at about its cost is a rival. Seeds 1-5,
#: 7-13, 21, 33, 78, 79 (32,000 scenes): broken promises 11 -> 7 of 28,830 successes; seeds 81-88,
#: never used before: 7 -> 4 of 14,410; success at 0.1 m / 1° within 0.07 points. Where both
#: searches end in the same wrong basin, nothing changes. The price is a second search on those
#: poses only (BENCHMARKS.md, "A second search for weak poses").
SECOND_SEARCH_BELOW_INLIERS = 32


# Plain Python on a few floats per map image: the check runs on every judged pose, and numpy's
# per-call overhead on arrays of 3-10 elements cost 30-70 µs per search (2-7 % of an estimate).


def inlier_ratios(inliers: np.ndarray, offsets: np.ndarray) -> tuple[list[float], list[int]]:
    """Per map image, the inlier ratio of a pose and the number of matches.

    Args:
        inliers: (N,) bool, the pose's inlier 2D-2D matches (rows of the flattened problem).
        offsets: (P + 1,) row offsets of the map images.

    Returns:
        ratios (P,) (0 where a map image has no match) and counts (P,).
    """
    bounds = offsets.tolist()
    counts = [b - a for a, b in zip(bounds[:-1], bounds[1:])]
    ratios = [
        int(np.count_nonzero(inliers[a:b])) / n if n else 0.0 for a, b, n in zip(bounds, bounds[1:], counts)
    ]
    return ratios, counts


def pair_sample_chance(ratios: Sequence[float], counts: Sequence[int], m: int) -> float:
    """The chance that one sample of ``m`` matches of a map image, drawn with probability in
    proportion to its matches among those with at least ``m``, is all inliers: ``Σ_j w_j r_j^m``
    (with replacement: a slight over-estimate for a few matches, so the bound stays on the
    side of refusing)."""
    total = sum(n for n in counts if n >= m)
    if total == 0:
        return 0.0
    return sum(n / total * float(r) ** m for r, n in zip(ratios, counts) if n >= m)


def missed_by_draws(p: float, samples: int) -> float:
    """``(1 - p)^samples``: no good sample in ``samples`` independent draws of chance ``p`` each."""
    return (1.0 - min(max(float(p), 0.0), 1.0)) ** max(samples, 0)


def missed_by_pairs(ratios: Sequence[float], counts: Sequence[int], m: int, samples: int) -> float:
    """The chance that fewer than two map images had an all-inlier sample of ``m`` matches among
    ``samples`` drawn in each (the two-stage search's stage 1 for every map image with at least
    ``m`` matches): ``1 - P(at least two)``, the images independent."""
    n = max(samples, 0)
    good = [
        1.0 - (1.0 - min(max(float(r), 0.0), 1.0) ** m) ** n if c >= m else 0.0
        for r, c in zip(ratios, counts)
    ]
    none = math.prod(1.0 - g for g in good)
    one = sum(g * math.prod(1.0 - h for k, h in enumerate(good) if k != j) for j, g in enumerate(good))
    return min(max(none + one, 0.0), 1.0)


def missed_by_all(missed: Iterable[Callable[[], float]]) -> float:
    """The chance that every one of several independent searches missed (the product of each
    one's ``missed()``), evaluated until it is at most :data:`MAX_MISS_PROBABILITY`: then it only
    bounds the product, which is all a check needs, and the other searches cost nothing."""
    product = 1.0
    for search in missed:
        product *= search()
        if product <= MAX_MISS_PROBABILITY:
            break
    return product


def rival_check_samples(inliers: np.ndarray, counts: np.ndarray, sample_size: int = 5) -> int:
    """Samples per map image of the short 6DoF check of a planar pose.

    Enough for an all-inlier ``sample_size`` sample with probability ``RIVAL_CHECK_CONFIDENCE``
    in the map image with the second-highest inlier ratio ``w`` of the planar pose (stage 2
    needs two map images): ``log(1 − c) / log(1 − w^m)`` (the RANSAC bound), between 2 and
    ``RIVAL_CHECK_ITERATIONS``. A 6DoF pose clearly better than the planar one has at least
    its inliers, so ``w`` errs on the side of more samples.

    Args:
        inliers: (P,) inliers per map image of the planar pose; counts: (P,) matches per map image.
    """
    ratios = sorted(
        (i / c for i, c in zip(inliers.tolist(), counts.tolist()) if c >= sample_size), reverse=True
    )
    if len(ratios) < 2:
        return RIVAL_CHECK_ITERATIONS
    clean = ratios[1] ** sample_size
    if clean >= 1.0:
        return 2
    if clean <= 0.0:
        return RIVAL_CHECK_ITERATIONS
    needed = math.log(1.0 - RIVAL_CHECK_CONFIDENCE) / math.log1p(-clean)
    return int(min(max(math.ceil(needed), 2), RIVAL_CHECK_ITERATIONS))
