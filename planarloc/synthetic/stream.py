"""Camera streams for sequential localization: ordered frames with dropped frames, kidnaps and
simulated wheel odometry, made from any posed image sequence (a rendered world, KITTI, TUM).

A *kidnap* moves the robot to another place between two frames without the wheels turning:
the ground truth jumps, the odometry does not move. A *dropped* frame is missing from the
stream; the motion between its neighbours is larger than usual.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.map.posed_image import PosedImage


@dataclass(frozen=True)
class StreamFrame:
    """One frame of a stream.

    Attributes:
        image: the posed image (its ``cam_from_world`` is the ground truth).
        stamp: seconds.
        odometry: simulated ``cam_from_odom`` of the wheel odometry at this frame.
        kidnapped: the robot was carried here from the previous frame's place.
    """

    image: PosedImage
    stamp: float
    odometry: Pose
    kidnapped: bool


def stream_order(
    n: int, kidnap_at: int | None = None, skip: int | None = None, drop: Iterable[int] = ()
) -> list[int]:
    """Indices of ``n`` frames in stream order.

    Without a kidnap: ``0..n-1``. With ``kidnap_at = k``: frames ``0..k-1``, then the robot is
    carried ``skip`` frames ahead (default: half of the rest) and streams ``k+skip..n-1``, then
    it is carried back to ``k`` and streams ``k..k+skip-1`` — two kidnaps, every frame once.
    ``drop`` removes frames (by index) from the result.

    Example:
        >>> stream_order(8, kidnap_at=2, skip=3, drop=[6])
        [0, 1, 5, 7, 2, 3, 4]
    """
    if n < 1:
        raise InputError(f"stream_order: need at least one frame, got {n}")
    order = list(range(n))
    if kidnap_at is not None:
        if not 1 <= kidnap_at < n - 1:
            raise InputError(f"kidnap_at: expected a frame index in 1..{n - 2}, got {kidnap_at}")
        skip = (n - kidnap_at) // 2 if skip is None else int(skip)
        if not 1 <= skip < n - kidnap_at:
            raise InputError(f"kidnap skip: expected 1..{n - kidnap_at - 1} frames, got {skip}")
        order = order[:kidnap_at] + order[kidnap_at + skip :] + order[kidnap_at : kidnap_at + skip]
    dropped = set(int(d) for d in drop)
    return [i for i in order if i not in dropped]


def simulate_odometry(
    truth: Sequence[Pose],
    kidnapped: Sequence[bool],
    rng: np.random.Generator,
    translation_std: float = 0.03,
    rotation_std_deg: float = 0.3,
) -> list[Pose]:
    """Wheel odometry along a stream: ``cam_from_odom`` per frame.

    Each frame-to-frame motion is the true one (identity across a kidnap) with its
    translation scaled by ``1 + N(0, translation_std)``, plus ``N(0, translation_std · |d|)``
    per axis, and its rotation perturbed by ``N(0, rotation_std_deg)`` per axis. The odometry
    frame is the first camera's frame.

    Args:
        truth: N ground-truth ``cam_from_world`` poses in stream order.
        kidnapped: (N,) frames reached by a kidnap.
        rng: random generator.
    """
    if len(truth) != len(kidnapped):
        raise InputError(f"truth and kidnapped: different lengths ({len(truth)} vs {len(kidnapped)})")
    out = [Pose.identity()] if truth else []
    for k in range(1, len(truth)):
        motion = Pose.identity() if kidnapped[k] else truth[k] @ truth[k - 1].inverse()
        d = motion.inverse().t
        dist = float(np.linalg.norm(d))
        d = d * (1.0 + rng.normal(0, translation_std)) + rng.normal(0, translation_std * dist, 3)
        R = Rotation.from_rotvec(np.radians(rng.normal(0, rotation_std_deg, 3))).as_matrix() @ motion.R
        out.append(Pose(R, -R @ d) @ out[-1])
    return out


def make_stream(
    images: Sequence[PosedImage],
    order: Sequence[int],
    rng: np.random.Generator,
    frame_period_s: float = 0.1,
    **odometry_noise: float,
) -> list[StreamFrame]:
    """The stream of ``images[order]``.

    Stamps are the images' timestamps when all have one, else ``index · frame_period_s``. A
    frame is ``kidnapped`` when ``order`` goes backwards or skips more than one frame that is
    not missing because of dropping — i.e. when its index is not the next one present after the
    previous frame's index in sorted order. ``odometry_noise`` goes to :func:`simulate_odometry`.
    """
    frames = [images[i] for i in order]
    present = sorted(set(order))
    nxt = {a: b for a, b in zip(present, present[1:])}
    kidnapped = [False] + [nxt.get(order[k - 1]) != order[k] for k in range(1, len(order))]
    timestamps = [f.timestamp for f in frames if f.timestamp is not None]
    if len(timestamps) == len(frames):  # every image has a timestamp
        stamps = [float(s) for s in timestamps]
    else:
        stamps = [f.index * frame_period_s for f in frames]
    if any(kidnapped):
        # a kidnap takes time: stamps keep increasing along the stream
        t, out = 0.0, []
        for k, s in enumerate(stamps):
            t = (
                s
                if k == 0
                else t + (frame_period_s if kidnapped[k] else max(s - stamps[k - 1], frame_period_s))
            )
            out.append(t)
        stamps = out
    odo = simulate_odometry([f.cam_from_world for f in frames], kidnapped, rng, **odometry_noise)
    return [StreamFrame(f, s, o, kd) for f, s, o, kd in zip(frames, stamps, odo, kidnapped)]
