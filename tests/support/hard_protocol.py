"""Scenes of ``benchmarks/robustness.py --protocol hard`` (3 map images, 1.5 px noise, 100 fixed
samples, 2 px), regenerated with the benchmark's seeding (``trial_seeds``), for tests that pin a
scene the benchmark found."""

from __future__ import annotations

import numpy as np

from planarloc.robust.options import RansacOptions
from planarloc.synthetic.scenes import SyntheticScene, make_scene

OUTLIERS = (0.0, 0.2, 0.4, 0.5, 0.6)  # the benchmark's outlier ratios, by index


def hard_protocol_scene(
    seed: int, matches_index: int, outlier_index: int, trial: int, matches: int
) -> tuple[SyntheticScene, RansacOptions]:
    """A scene and the benchmark's paper options for it (exactly 100 samples, 2 px, no structure)."""
    ss = np.random.SeedSequence([seed, matches_index, outlier_index, trial])
    sc = make_scene(
        np.random.default_rng(ss),
        num_refs=3,
        matches_per_pair=matches,
        noise_px=1.5,
        outlier_ratio=OUTLIERS[outlier_index],
    )
    options = RansacOptions(
        max_iterations=100,
        min_iterations=100,
        threshold_px=2.0,
        seed=int(ss.generate_state(1)[0]),
        structure="none",
    )
    return sc, options
