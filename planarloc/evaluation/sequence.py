"""Evaluate sequential localization: every frame counts, confident errors, relocalization time.

A frame succeeds at ``(τ_t, τ_R)`` when the stream reported a usable pose (``localized`` or
``predicted``) within ``τ_t`` metres and ``τ_R`` degrees of the ground truth; a ``lost`` frame is a
failure at every threshold — no frame is skipped. A *confident-wrong* frame is one reported
``localized`` whose pose is more than 1 m or 20° off (``predicted`` frames beyond that are
counted apart). Relocalization (OpenLORIS-style): the frames and seconds from the start, and
from each kidnap (a ground-truth jump the robot did not drive), to the first frame whose
reported pose is correct at the first threshold.

Speed (:func:`evaluate_stream`): the frames are handed to the stream like a camera would. Without
``rate_hz`` each frame arrives when the previous pose has been returned (the sustained rate of
the localizer); with ``rate_hz`` frame ``k`` arrives ``k / rate_hz`` seconds after the first,
and a frame that is not taken before the next one arrives is dropped (a camera driver with a
queue of one: the newest frame wins) — a ``dropped`` frame has no pose and fails at every
threshold. ``frames_per_second`` is the sustained rate after the first frame (frames posed
after the first, over the time from the first pose to the last); ``latency_ms`` (arrival →
pose) is over the frames after the first, whose latency (it waits for the stream's first fix) is
reported apart; ``cpu_ms_per_frame`` is the CPU time of those steps in the calling thread (with
background fixes: the frame path alone).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from planarloc.evaluation.queries import (
    THRESHOLDS,
    center_tuple,
    compared,
    quat_wxyz_tuple,
    threshold_name,
    with_truth,
)
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.localize.records import error_record, frame_record
from planarloc.localize.sequence import FrameStatus, SequenceEstimate, SequenceLocalizer
from planarloc.map.posed_image import PosedImage

WRONG_M, WRONG_DEG = 1.0, 20.0
#: the schema of :func:`summarize_sequence`'s JSON (``docs/schema/sequence-evaluation.schema.json``)
SCHEMA = "planarloc.sequence-evaluation/1"
#: status of a frame the camera replaced before the stream took it (``evaluate_stream(rate_hz=...)``)
DROPPED = "dropped"


@dataclass(frozen=True)
class FrameResult:
    """Outcome of one frame of a stream; errors are NaN when no pose was reported.

    Poses are ``cam_from_world``: ``*_center`` the camera centre in the world, ``*_quat_wxyz``
    the rotation. ``latency_s``: arrival → pose; ``finished_s``: when the pose was returned
    (seconds since the stream started); ``late``: the stream said the pose came too late;
    ``success``: the pose is usable (``localized`` or ``predicted``); ``timestamp``: the stamp
    (for TUM files); ``reason``: why a frame could not be processed (status ``error``); ``cpu_s``:
    the CPU time of its step in the calling thread.
    """

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
    estimate_quat_wxyz: tuple[float, float, float, float] | None = None
    truth_quat_wxyz: tuple[float, float, float, float] | None = None
    latency_s: float = float("nan")
    finished_s: float = float("nan")
    late: bool = False
    success: bool = False
    timestamp: float | None = None
    reason: str = ""
    cpu_s: float = float("nan")
    #: the frame's record (:func:`planarloc.localize.records.frame_record`), as ``localize --sequence``
    #: writes it
    record: dict = field(default_factory=dict, compare=False, repr=False)

    def to_dict(self) -> dict:
        """The evaluation's entry of this frame: its record (docs/schema/record.schema.json) with
        the ground truth, the errors (null without a pose), ``kidnapped`` and ``finished_s``."""
        return {
            **with_truth(self),
            "kidnapped": self.kidnapped,
            "finished_s": self.finished_s,
        }


def frame_result(
    image: PosedImage, est: SequenceEstimate, kidnapped: bool, finished_s: float = float("nan")
) -> FrameResult:
    """The outcome of one frame; ``finished_s``: when its pose was returned (seconds since the
    stream started)."""
    truth = image.cam_from_world
    cmp = compared(est.pose, truth)
    return FrameResult(
        image.name,
        est.stamp,
        est.status,
        est.fix_status,
        est.motion_source,
        bool(kidnapped),
        cmp.translation_error_m,
        cmp.rotation_error_deg,
        float(est.position_std_m),
        float(est.seconds),
        cmp.center,
        center_tuple(truth.center),
        cmp.quat_wxyz,
        quat_wxyz_tuple(truth.quat_wxyz),
        float(est.latency_s),
        float(finished_s),
        bool(est.late),
        bool(est.success),
        float(est.stamp),
        cpu_s=float(est.cpu_s),
        record=frame_record(image.name, est),
    )


def unposed_result(
    image: PosedImage, stamp: float, kidnapped: bool, status: str = "dropped", reason: str = ""
) -> FrameResult:
    """A frame without a pose: one the stream never saw (:data:`DROPPED`), or one it could not
    process (``"error"``, with its reason)."""
    return FrameResult(
        image.name,
        float(stamp),
        status,
        "none",
        "none",
        bool(kidnapped),
        float("nan"),
        float("nan"),
        float("inf"),
        0.0,
        None,
        center_tuple(image.cam_from_world.center),
        None,
        quat_wxyz_tuple(image.cam_from_world.quat_wxyz),
        timestamp=float(stamp),
        reason=" ".join(str(reason).split()),
        record=error_record(
            image.name,
            reason or "the camera replaced this frame before the stream took it",
            kind="frame",
            stamp=stamp,
            status=status,
        ),
    )


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
    return r.status in USABLE and r.translation_error_m < t and r.rotation_error_deg < rot


#: statuses whose pose counts (``lost``, ``dropped`` and ``error`` frames fail)
USABLE = (FrameStatus.LOCALIZED.value, FrameStatus.PREDICTED.value)


def relocalization(results: Sequence[FrameResult], threshold: tuple[float, float] = THRESHOLDS[0]) -> dict:
    """Frames and seconds from the start and from each kidnap to the first correct pose
    (0 frames: the event's own frame was correct); ``None`` when never reached."""

    def delay(start: int, end: int) -> dict | None:
        for k in range(start, end):
            if _correct(results[k], *threshold):
                return {
                    "frame": results[start].name,
                    "frames": k - start,
                    "seconds": float(results[k].stamp - results[start].stamp),
                }
        return None

    events = [k for k, r in enumerate(results) if r.kidnapped]
    bounds = [0, *events, len(results)]
    kidnaps = [delay(a, b) for a, b in zip(bounds[1:-1], bounds[2:])]
    out: dict[str, object] = {
        "threshold": threshold_name(*threshold),
        "start": delay(0, bounds[1]) if results else None,
        "kidnaps": kidnaps,
    }
    found = [d["frames"] for d in kidnaps if d is not None]
    out["max_frames_after_kidnap"] = max(found) if found and len(found) == len(events) else None
    return out


def _speed(results: Sequence[FrameResult]) -> dict:
    """Sustained frames per second and latency after the first posed frame (module docstring)."""
    done = [r for r in results if np.isfinite(r.finished_s)]
    lat = np.array([r.latency_s for r in done[1:]], dtype=float)
    span = done[-1].finished_s - done[0].finished_s if len(done) > 1 else 0.0
    return {
        "frames_per_second": float((len(done) - 1) / span) if span > 0 else None,
        "latency_ms": (
            {
                "p50": 1e3 * float(np.percentile(lat, 50)),
                "p99": 1e3 * float(np.percentile(lat, 99)),
                "max": 1e3 * float(lat.max()),
            }
            if len(lat)
            else None
        ),
        "first_frame_latency_ms": 1e3 * done[0].latency_s if done else None,
        "cpu_ms_per_frame": 1e3 * float(np.mean([r.cpu_s for r in done[1:]])) if len(done) > 1 else None,
        "late_frames": int(sum(r.late for r in done)),  # every frame the stream said was late (its own count)
        "dropped_frames": int(sum(r.status == DROPPED for r in results)),
    }


def summarize_sequence(results: Sequence[FrameResult], **extra: object) -> dict:
    """The `evaluate --sequential` JSON: success over every frame at the paper's thresholds,
    statuses, confident-wrong counts, relocalization delays, speed and latency."""
    n = len(results)
    t = np.array([r.translation_error_m for r in results], dtype=float)
    rot = np.array([r.rotation_error_deg for r in results], dtype=float)
    status = np.array([r.status for r in results])
    usable = np.isin(status, USABLE)
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
    seconds = np.array([r.seconds for r in results if np.isfinite(r.finished_s)], dtype=float)
    loc = status == FrameStatus.LOCALIZED.value
    return {
        "schema": SCHEMA,
        "frames": n,
        "success": success,
        "status_counts": counts,
        "frames_with_pose": int(np.isfinite(t).sum()),
        "confident_wrong": int((loc & wrong).sum()),
        "predicted_wrong": int(((status == FrameStatus.PREDICTED.value) & wrong).sum()),
        "max_translation_error_m": float(np.max(t[usable])) if usable.any() else None,
        "rejected_fixes": int(sum(r.fix_status == "rejected" for r in results)),
        "median_translation_error_m": float(np.median(t[usable])) if usable.any() else None,
        "median_rotation_error_deg": float(np.median(rot[usable])) if usable.any() else None,
        "relocalization": relocalization(results),
        "seconds_per_frame": float(seconds.mean()) if len(seconds) else None,
        **_speed(results),
        **extra,
        "per_frame": [r.to_dict() for r in results],
    }


def evaluate_stream(
    seq: SequenceLocalizer,
    images: Sequence[PosedImage],
    stamps: Sequence[float],
    odometry: Sequence[Pose | None] | None = None,
    kidnapped: Sequence[bool] | None = None,
    progress: Callable[[int, int], None] | None = None,
    rate_hz: float | None = None,
    on_frame: Callable[[PosedImage, SequenceEstimate], None] | None = None,
) -> list[FrameResult]:
    """Run ``seq`` over the stream ``images`` (in order) and compare each frame with its ground truth.

    Args:
        seq: the stream localizer; it is reset first.
        images: the frames, in stream order, with their ground truth.
        stamps: (N,) their stamps (seconds, increasing).
        odometry: (N,) wheel odometry ``cam_from_odom`` per frame, or None.
        kidnapped: (N,) kidnap frames for the relocalization figures (default:
            :func:`ground_truth_jumps`).
        progress: called with (frames done, N).
        rate_hz: frames arrive at this rate, and late ones are dropped; None: each frame
            arrives when the previous one is done (module docstring).
        on_frame: called with each frame and its estimate (e.g. a Rerun recording).

    Returns:
        One :class:`FrameResult` per frame (``dropped`` ones included; a frame the stream
        refused — an unreadable image, a size its camera does not have — has status ``error``
        and its reason, and the stream goes on).
    """
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz: expected a frame rate > 0, got {rate_hz}")
    seq.reset()
    kidnapped = (
        list(kidnapped) if kidnapped is not None else ground_truth_jumps([i.cam_from_world for i in images])
    )
    out: list[FrameResult] = []
    start = time.perf_counter()
    k = 0
    while k < len(images):
        arrival = time.perf_counter()
        if rate_hz is not None:
            now = time.perf_counter()
            latest = min(int((now - start) * rate_hz), len(images) - 1)  # the newest frame that has arrived
            for j in range(k, latest):  # the camera replaced them
                out.append(unposed_result(images[j], stamps[j], kidnapped[j]))
            k = max(k, latest)
            arrival = start + k / rate_hz
            if arrival > now:
                time.sleep(arrival - now)
        image = images[k]
        try:  # a frame that cannot be processed is recorded with its reason; the stream goes on
            est = seq.step(
                image.path,
                image.camera,
                stamps[k],
                None if odometry is None else odometry[k],
                arrival=arrival,
            )
        except (InputError, OSError) as exc:
            reason = f"{image.path}: {exc.strerror or exc}" if isinstance(exc, OSError) else str(exc)
            out.append(unposed_result(image, stamps[k], kidnapped[k], "error", reason))
        else:
            out.append(frame_result(image, est, kidnapped[k], time.perf_counter() - start))
            if on_frame is not None:
                on_frame(image, est)
        k += 1
        if progress:
            progress(len(out), len(images))
    return out
