"""Ranges of RansacOptions fields and PairMatches ids that used to be accepted silently."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.options import RansacOptions
from planarloc.robust.pair_matches import PairMatches


@pytest.mark.parametrize("field", ["map_position_std_m", "map_rotation_std_deg", "track_min_angle_deg",
                                   "min_collinearity_ratio"])
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
