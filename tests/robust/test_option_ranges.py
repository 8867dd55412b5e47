"""Ranges of RansacOptions fields and PairMatches ids that used to be accepted silently."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.options import RansacOptions
from planarloc.robust.pair_matches import PairMatches


@pytest.mark.parametrize(
    "field", ["map_position_std_m", "map_rotation_std_deg", "track_min_angle_deg", "min_collinearity_ratio"]
)
def test_negative_values_rejected(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        RansacOptions(**{field: -0.1})
    RansacOptions(**{field: 0.0})  # zero is meaningful (perfect map, no angle / collinearity test)


def test_collinearity_ratio_above_one_rejected() -> None:
    with pytest.raises(ValueError, match="min_collinearity_ratio"):
        RansacOptions(min_collinearity_ratio=1.5)


def test_fractional_query_indices_rejected() -> None:
    cam = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    pts = np.random.default_rng(0).uniform(0, 400, (5, 2))
    ok = PairMatches(Pose.identity(), cam, pts, pts, query_indices=np.array([0.0, 1, 2, 3, 4]))
    assert ok.query_indices.dtype == np.int64 and list(ok.query_indices) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="whole numbers"):
        PairMatches(Pose.identity(), cam, pts, pts, query_indices=np.array([0, 1, 2.5, 3, 4]))


def test_with_iterations_sets_exact_budget_on_a_copy() -> None:
    base = RansacOptions(max_iterations=50, min_iterations=20, threshold_px=1.5, seed=3)
    short = base.with_iterations(7)
    assert (short.min_iterations, short.max_iterations) == (7, 7)
    assert (base.min_iterations, base.max_iterations) == (20, 50)  # the original is untouched
    assert short.threshold_px == 1.5 and short.seed == 3 and short.structure == base.structure
    assert base.with_iterations(500).max_iterations == 50  # clipped to the budget
    with pytest.raises(ValueError, match="with_iterations"):
        base.with_iterations(0)


@pytest.mark.parametrize("value", ["2", None, True, [2.0]])
def test_non_numeric_thresholds_rejected(value) -> None:
    with pytest.raises(ValueError, match="threshold_px: expected a number"):
        RansacOptions(threshold_px=value)
