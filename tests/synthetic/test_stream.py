"""Stream order, kidnap flags, stamps and simulated odometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.map.posed_image import PosedImage
from planarloc.robust.pose_graph import so3_exp
from planarloc.synthetic.stream import make_stream, simulate_odometry, stream_order

CAM = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


def _images(n: int) -> list[PosedImage]:
    return [
        PosedImage(
            f"{k}.png",
            Path(f"{k}.png"),
            Pose.from_center(so3_exp([[0, 0.1 * k, 0]])[0], [0, 0, 1.0 * k]),
            CAM,
            k,
        )
        for k in range(n)
    ]


def test_order_keeps_every_frame_once_and_drops() -> None:
    assert stream_order(5) == [0, 1, 2, 3, 4]
    order = stream_order(10, kidnap_at=3)
    assert sorted(order) == list(range(10)) and order[:4] == [0, 1, 2, 6]
    assert stream_order(8, kidnap_at=2, skip=3, drop=[6]) == [0, 1, 5, 7, 2, 3, 4]
    with pytest.raises(InputError, match="kidnap_at"):
        stream_order(5, kidnap_at=4)


def test_kidnaps_are_jumps_not_drops_and_stamps_increase() -> None:
    frames = make_stream(_images(8), stream_order(8, kidnap_at=2, skip=3, drop=[6]), np.random.default_rng(0))
    assert [f.kidnapped for f in frames] == [False, False, True, False, True, False, False]
    stamps = [f.stamp for f in frames]
    assert np.all(np.diff(stamps) > 0)
    assert stamps[3] - stamps[2] == pytest.approx(0.2)  # 5 -> 7: one frame dropped


def test_odometry_follows_the_truth_and_ignores_kidnaps() -> None:
    images = _images(6)
    truth = [images[i].cam_from_world for i in (0, 1, 4, 5)]
    odo = simulate_odometry(truth, [False, False, True, False], np.random.default_rng(0), 0.0, 0.0)
    for k in (1, 3):
        measured = odo[k] @ odo[k - 1].inverse()
        assert max(pose_errors(measured, truth[k] @ truth[k - 1].inverse())) < 1e-9
    assert max(pose_errors(odo[2], odo[1])) < 1e-9  # carried: the wheels did not turn
    noisy = simulate_odometry(truth, [False] * 4, np.random.default_rng(0), 0.05, 1.0)
    err = pose_errors(noisy[1] @ noisy[0].inverse(), truth[1] @ truth[0].inverse())
    assert 0 < err[0] < 0.5 and 0 < err[1] < 5
