"""Sequential metrics: every frame counted, confident-wrong, relocalization delays, a camera's
rate with dropped frames, frames the stream refuses."""

from __future__ import annotations

import time

import numpy as np
import pytest

from planarloc.evaluation.sequence import (
    DROPPED,
    FrameResult,
    evaluate_stream,
    ground_truth_jumps,
    relocalization,
    summarize_sequence,
)
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.localize.sequence import SequenceEstimate
from planarloc.map.posed_image import PosedImage


def _r(k: int, status: str, t_err: float, kidnapped: bool = False) -> FrameResult:
    return FrameResult(
        f"{k}",
        0.1 * k,
        status,
        "accepted",
        "odometry",
        kidnapped,
        t_err,
        1.0 if t_err == t_err else float("nan"),
        0.05,
        0.2,
        None,
        (0.0, 0.0, 0.0),
    )


def test_every_frame_counts_and_lost_is_a_failure() -> None:
    res = [
        _r(0, "lost", float("nan")),
        _r(1, "localized", 0.1),
        _r(2, "predicted", 0.2),
        _r(3, "lost", 0.01),
        _r(4, "localized", 1.5),
        _r(5, "predicted", 3.0),
    ]
    s = summarize_sequence(res)
    assert s["frames"] == 6 and s["success"]["0.25m/10deg"] == 100 * 2 / 6
    assert s["success"]["1m/20deg"] == 100 * 2 / 6
    assert s["confident_wrong"] == 1 and s["predicted_wrong"] == 1
    assert s["status_counts"] == {"lost": 2, "localized": 2, "predicted": 2}


def test_relocalization_counts_frames_from_start_and_each_kidnap() -> None:
    res = [
        _r(0, "lost", float("nan")),
        _r(1, "localized", 0.05),
        _r(2, "localized", 0.05),
        _r(3, "predicted", 9.0, kidnapped=True),
        _r(4, "lost", 9.0),
        _r(5, "localized", 0.1),
        _r(6, "localized", 9.0, kidnapped=True),
    ]
    r = relocalization(res)
    assert r["start"]["frames"] == 1
    assert [k["frames"] if k else None for k in r["kidnaps"]] == [2, None]
    assert r["max_frames_after_kidnap"] is None  # one kidnap never recovered


def test_ground_truth_jumps() -> None:
    poses = [Pose.from_center(Pose.identity().R, [0, 0, z]) for z in (0, 1, 2, 4, 20, 21)]
    assert ground_truth_jumps(poses) == [False, False, False, False, True, False]


class _SlowStream:
    """A stream localizer that takes ``seconds`` per frame and always reports the truth (the
    evaluation's clock and dropping are what is tested)."""

    def __init__(self, truth: dict, seconds: float) -> None:
        self.truth, self.seconds, self.steps = truth, seconds, []

    def reset(self) -> None:
        self.steps = []

    def step(self, path, camera, stamp, odometry=None, arrival=None) -> SequenceEstimate:
        time.sleep(self.seconds)
        self.steps.append(stamp)
        if path == "bad.png":
            raise InputError("bad.png: cannot read image")
        pose = self.truth[path]
        return SequenceEstimate(
            stamp,
            "localized",
            pose,
            np.eye(6) * 1e-4,
            0.01,
            0.1,
            seconds=self.seconds,
            latency_s=time.perf_counter() - arrival,
        )


def _images(n: int) -> list[PosedImage]:
    cam = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    return [
        PosedImage(f"{k}.png", f"{k}.png", Pose.from_center(np.eye(3), [0, 0, k]), cam, index=k)
        for k in range(n)
    ]


def test_a_camera_rate_drops_frames_the_stream_cannot_take() -> None:
    """Frames every 20 ms, 50 ms per frame: about 3 of 5 frames are dropped and counted; the
    sustained rate is the stream's (~20 frames/s) and latency includes the wait."""
    images = _images(20)
    seq = _SlowStream({im.path: im.cam_from_world for im in images}, 0.05)
    res = evaluate_stream(seq, images, [0.02 * k for k in range(20)], rate_hz=50.0)
    s = summarize_sequence(res)
    dropped = [r for r in res if r.status == DROPPED]
    assert len(res) == 20 and s["dropped_frames"] == len(dropped) >= 8 and len(seq.steps) == 20 - len(dropped)
    assert all(np.isnan(r.translation_error_m) for r in dropped)
    assert s["success"]["0.25m/10deg"] == pytest.approx(100 * len(seq.steps) / 20)  # a dropped frame fails
    assert 10 < s["frames_per_second"] < 25 and s["latency_ms"]["p50"] >= 50
    unpaced = summarize_sequence(evaluate_stream(seq, images, [0.02 * k for k in range(20)]))
    assert unpaced["dropped_frames"] == 0 and unpaced["frames_with_pose"] == 20
    assert unpaced["frames_per_second"] == pytest.approx(20, rel=0.3)


def test_a_frame_the_stream_refuses_is_an_error_and_the_stream_goes_on() -> None:
    images = _images(4)
    images[2] = PosedImage("bad.png", "bad.png", images[2].cam_from_world, images[2].camera, index=2)
    seq = _SlowStream({im.path: im.cam_from_world for im in images}, 0.0)
    res = evaluate_stream(seq, images, [0.1 * k for k in range(4)])
    assert [r.status for r in res] == ["localized", "localized", "error", "localized"]
    assert res[2].reason == "bad.png: cannot read image"
    assert summarize_sequence(res)["status_counts"]["error"] == 1
