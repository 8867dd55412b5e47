"""Sequential metrics: every frame counted, confident-wrong, relocalization delays."""

from __future__ import annotations

from planarloc.evaluation.sequence import FrameResult, ground_truth_jumps, relocalization, summarize_sequence
from planarloc.geometry.pose import Pose


def _r(k: int, status: str, t_err: float, kidnapped: bool = False) -> FrameResult:
    return FrameResult(f"{k}", 0.1 * k, status, "accepted", "odometry", kidnapped, t_err,
                       1.0 if t_err == t_err else float("nan"), 0.05, 0.2, None, (0.0, 0.0, 0.0))


def test_every_frame_counts_and_lost_is_a_failure() -> None:
    res = [_r(0, "lost", float("nan")), _r(1, "localized", 0.1), _r(2, "predicted", 0.2), _r(3, "lost", 0.01),
           _r(4, "localized", 1.5), _r(5, "predicted", 3.0)]
    s = summarize_sequence(res)
    assert s["frames"] == 6 and s["success"]["0.25m/10deg"] == 100 * 2 / 6
    assert s["success"]["1m/20deg"] == 100 * 2 / 6
    assert s["confident_wrong"] == 1 and s["predicted_wrong"] == 1
    assert s["status_counts"] == {"lost": 2, "localized": 2, "predicted": 2}


def test_relocalization_counts_frames_from_start_and_each_kidnap() -> None:
    res = [_r(0, "lost", float("nan")), _r(1, "localized", 0.05), _r(2, "localized", 0.05),
           _r(3, "predicted", 9.0, kidnapped=True), _r(4, "lost", 9.0), _r(5, "localized", 0.1),
           _r(6, "localized", 9.0, kidnapped=True)]
    r = relocalization(res)
    assert r["start"]["frames"] == 1
    assert [k["frames"] if k else None for k in r["kidnaps"]] == [2, None]
    assert r["max_frames_after_kidnap"] is None      # one kidnap never recovered


def test_ground_truth_jumps() -> None:
    poses = [Pose.from_center(Pose.identity().R, [0, 0, z]) for z in (0, 1, 2, 4, 20, 21)]
    assert ground_truth_jumps(poses) == [False, False, False, False, True, False]
