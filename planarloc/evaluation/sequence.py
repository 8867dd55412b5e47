"""Evaluate sequential localization: every frame counts, confident errors, relocalization time.

A frame succeeds at ``(τ_t, τ_R)`` when the stream reported a usable pose (``localized`` or
``predicted``) within ``τ_t`` metres and ``τ_R`` degrees of the ground truth; a ``lost`` frame is a
failure at every threshold — no frame is skipped. A *confident-wrong* frame is one reported
``localized`` whose pose is more than 1 m or 20° off (``predicted`` frames beyond that are
counted apart). Relocalization (OpenLORIS-style): the frames and seconds from the start, and
from each kidnap (a ground-truth jump the robot did not drive), to the first frame whose
reported pose is correct at the first threshold.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from planarloc.evaluation.queries import THRESHOLDS, threshold_name
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.localize.sequence import FrameStatus, SequenceEstimate, SequenceLocalizer
from planarloc.map.posed_image import PosedImage

WRONG_M, WRONG_DEG = 1.0, 20.0


@dataclass(frozen=True)
class FrameResult:
    """Outcome of one frame of a stream; errors are NaN when no pose was reported."""

    name: str
    stamp: float
    status: str
    fix_status: str
    motion_source: str
    kidnapped: bool
    translation_error_m: float
    rotation_error_deg: float
    position_std_m: float
    seconds: float
    estimate_center: tuple[float, float, float] | None
    truth_center: tuple[float, float, float]


def frame_result(image: PosedImage, est: SequenceEstimate, kidnapped: bool) -> FrameResult:
    if est.pose is not None:
        t_err, r_err = pose_errors(est.pose, image.cam_from_world)
        c = tuple(float(v) for v in est.pose.center)
    else:
        t_err, r_err, c = float("nan"), float("nan"), None
    return FrameResult(image.name, est.stamp, est.status, est.fix_status, est.motion_source, bool(kidnapped),
                       t_err, r_err, float(est.position_std_m), float(est.seconds), c,
                       tuple(float(v) for v in image.cam_from_world.center))


def ground_truth_jumps(truth: Sequence[Pose], min_jump_m: float = 3.0, factor: float = 4.0) -> list[bool]:
    """(N,) True where the ground-truth centre moved more than ``max(min_jump_m, factor ×
    the median step)`` since the previous frame (a kidnap, for evaluation)."""
    c = np.array([p.center for p in truth]).reshape(-1, 3)
    if len(c) < 2:
        return [False] * len(c)
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    limit = max(min_jump_m, factor * float(np.median(step)))
    return [False] + [bool(s > limit) for s in step]


def _correct(r: FrameResult, t: float, rot: float) -> bool:
    return r.status != FrameStatus.LOST.value and r.translation_error_m < t and r.rotation_error_deg < rot


def relocalization(results: Sequence[FrameResult], threshold: tuple[float, float] = THRESHOLDS[0]) -> dict:
    """Frames and seconds from the start and from each kidnap to the first correct pose
    (0 frames: the event's own frame was correct); ``None`` when never reached."""

    def delay(start: int, end: int) -> dict | None:
        for k in range(start, end):
            if _correct(results[k], *threshold):
                return {"frame": results[start].name, "frames": k - start,
                        "seconds": float(results[k].stamp - results[start].stamp)}
        return None

    events = [k for k, r in enumerate(results) if r.kidnapped]
    bounds = [0, *events, len(results)]
    out = {"threshold": threshold_name(*threshold), "start": delay(0, bounds[1]) if results else None,
           "kidnaps": [delay(a, b) for a, b in zip(bounds[1:-1], bounds[2:])]}
    found = [d["frames"] for d in out["kidnaps"] if d is not None]
    out["max_frames_after_kidnap"] = max(found) if found and len(found) == len(events) else None
    return out


def summarize_sequence(results: Sequence[FrameResult], **extra: object) -> dict:
    """The `evaluate --sequential` JSON: success over every frame at the paper's thresholds,
    statuses, confident-wrong counts, relocalization delays, time per frame."""
    n = len(results)
    t = np.array([r.translation_error_m for r in results], dtype=float)
    rot = np.array([r.rotation_error_deg for r in results], dtype=float)
    status = np.array([r.status for r in results])
    usable = status != FrameStatus.LOST.value
    with np.errstate(invalid="ignore"):
        wrong = (t > WRONG_M) | (rot > WRONG_DEG)
    success = {}
    for tt, rr in THRESHOLDS:
        with np.errstate(invalid="ignore"):
            hit = usable & (t < tt) & (rot < rr)
        success[threshold_name(tt, rr)] = 100.0 * float(hit.sum()) / max(n, 1)
    counts: dict[str, int] = {}
    for s in status:
        counts[str(s)] = counts.get(str(s), 0) + 1
    seconds = np.array([r.seconds for r in results], dtype=float)
    loc = status == FrameStatus.LOCALIZED.value
    return {
        "frames": n,
        "success": success,
        "status_counts": counts,
        "frames_with_pose": int(np.isfinite(t).sum()),
        "confident_wrong": int((loc & wrong).sum()),
        "predicted_wrong": int(((status == FrameStatus.PREDICTED.value) & wrong).sum()),
        "rejected_fixes": int(sum(r.fix_status == "rejected" for r in results)),
        "median_translation_error_m": float(np.median(t[usable])) if usable.any() else None,
        "median_rotation_error_deg": float(np.median(rot[usable])) if usable.any() else None,
        "relocalization": relocalization(results),
        "seconds_per_frame": float(seconds.mean()) if n else None,
        "frames_per_second": float(1.0 / seconds[1:].mean()) if n > 1 and seconds[1:].mean() > 0 else None,
        **extra,
        "per_frame": [asdict(r) for r in results],
    }


def evaluate_stream(
    seq: SequenceLocalizer,
    images: Sequence[PosedImage],
    stamps: Sequence[float],
    odometry: Sequence[Pose | None] | None = None,
    kidnapped: Sequence[bool] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameResult]:
    """Run ``seq`` over the stream ``images`` (in order) and compare each frame with its ground truth.

    ``kidnapped`` marks kidnap frames for the relocalization figures (default:
    :func:`ground_truth_jumps`). ``seq`` is reset first.
    """
    seq.reset()
    kidnapped = list(kidnapped) if kidnapped is not None else ground_truth_jumps([i.cam_from_world for i in images])
    out = []
    for k, image in enumerate(images):
        est = seq.step(image.path, image.camera, stamps[k], None if odometry is None else odometry[k])
        out.append(frame_result(image, est, kidnapped[k]))
        if progress:
            progress(k + 1, len(images))
    return out
