"""Named stream perturbations: what a robot's camera stream does to a localizer besides moving.

Each case is a pure function ``(frames, rng) -> frames`` over a list of :class:`CaseFrame` (image,
camera, stamp, truth, odometry): it never changes its input, and with the same generator it
gives the same stream. ``benchmarks/stream_trust.py`` replays the shared KITTI and generated
worlds through :class:`~planarloc.localize.sequence.SequenceLocalizer` under every case; the unit
tests use them on rendered frames.

The registry :data:`CASES` (name → :class:`StreamCase`):

- ``default``: the stream as recorded.
- ``dropped``: 20–30 % of the frames removed at random (never the first), true stamps: the
  stamp gaps tell how much time (and motion) is missing.
- ``fixed-rate``: the same drop, but the stamps re-written at the nominal rate (the median stamp
  gap of the input), as a camera driver that stamps frames by count does: the stamp gaps lie
  about the motion.
- ``black``: about 10 % of the frames after the first three replaced by all-zero images (lens
  cap, a dropped exposure), one pair of them in a row; truth, stamp and odometry kept.
- ``corrupt``: about 10 % of the frames after the first three replaced by bytes that are not an
  image: zero-length, random bytes, a PNG cut in half (in turn); truth, stamp and odometry kept.
  The stream should refuse each with a clear error (``InputError``) or a failure status and go on.
- ``stop-and-go``: the robot stops twice (at a third and two thirds of the stream) for
  ``stop_frames`` frames (1 s at 10 Hz): the same image, truth and odometry repeated with stamps
  advancing at the nominal rate; the frames after a stop are stamped that much later.
- ``kidnap``: after a quarter of the stream the robot is carried half of the rest ahead, streams
  to the end, then is carried back and streams the frames it skipped
  (as :func:`planarloc.synthetic.stream.stream_order`): two kidnaps, every frame once; a kidnap
  takes one nominal frame period, the wheel odometry does not move across it.
- ``jitter``: every stamp off its true time by a uniform random ±30 ms (kept increasing).

Odometry is the wheel odometry's ``cam_from_odom`` per frame (only differences between frames
mean anything): a dropped frame leaves its neighbours' odometry as it was; a repeated frame has
the odometry of the frame it repeats; across a kidnap the odometry is chained with no motion.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from planarloc.features.images import read_gray
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError

#: kinds of :attr:`CaseFrame.kind`
FRAME, BLACK, CORRUPT, STOPPED = "frame", "black", "corrupt", "stopped"


@dataclass(frozen=True)
class CaseFrame:
    """One frame of a (perturbed) stream.

    Attributes:
        image: what the stream is given: (H, W) uint8 array, bytes (JPEG/PNG, or garbage in the
            ``corrupt`` case) or an image file.
        camera: the image's intrinsics.
        stamp: seconds, increasing along the stream.
        truth: ground-truth ``cam_from_world`` of the camera at this frame.
        odometry: the wheel odometry's ``cam_from_odom`` at this frame, or None.
        name: the source frame's name (a repeated frame keeps it).
        kind: :data:`FRAME`, :data:`BLACK` (an all-zero image), :data:`CORRUPT` (bytes that
            are not an image) or :data:`STOPPED` (a repeat of the previous frame: the robot
            stands still).
        kidnapped: the robot was carried here from the previous frame's place.
        capture_time: seconds on the stream's clock when the camera took the frame, where
            ``stamp`` lies about it (``fixed-rate``, ``jitter``); None: ``stamp`` is the truth.
            A replay that paces frames as a camera delivers them uses :attr:`true_time`.
    """

    image: object
    camera: Camera
    stamp: float
    truth: Pose
    odometry: Pose | None = None
    name: str = ""
    kind: str = FRAME
    kidnapped: bool = False
    capture_time: float | None = None

    @property
    def true_time(self) -> float:
        """When the frame was taken (seconds): :attr:`capture_time`, else :attr:`stamp`."""
        return self.stamp if self.capture_time is None else self.capture_time


def frames_from_stream(stream: Sequence, load: bool = True) -> list[CaseFrame]:
    """:class:`CaseFrame` of each frame of a :func:`planarloc.synthetic.stream.make_stream`
    stream (anything with ``image`` (a :class:`~planarloc.map.posed_image.PosedImage`), ``stamp``,
    ``odometry`` and ``kidnapped``; its simulated odometry kept); ``load``: images as (H, W)
    uint8 arrays, else their files."""
    return [
        CaseFrame(
            read_gray(f.image.path) if load else f.image.path,
            f.image.camera,
            float(f.stamp),
            f.image.cam_from_world,
            f.odometry,
            f.image.name,
            kidnapped=bool(f.kidnapped),
        )
        for f in stream
    ]


def nominal_period(frames: Sequence[CaseFrame]) -> float:
    """The median gap between consecutive stamps (seconds).

    Raises:
        InputError: fewer than two frames, or stamps that do not increase.
    """
    if len(frames) < 2:
        raise InputError(f"nominal_period: need at least 2 frames, got {len(frames)}")
    gaps = np.diff([f.stamp for f in frames])
    period = float(np.median(gaps))
    if not period > 0:
        raise InputError(f"nominal_period: stamps must increase, median gap {period}")
    return period


# ---- the cases ----------------------------------------------------------------------------------
def default(frames: Sequence[CaseFrame], rng: np.random.Generator) -> list[CaseFrame]:
    """The stream as recorded."""
    return list(frames)


def _drop(
    frames: Sequence[CaseFrame], rng: np.random.Generator, fraction: tuple[float, float]
) -> list[CaseFrame]:
    """``frames`` without a random ``fraction`` (drawn uniformly in the range) of them, never the first."""
    n = len(frames)
    k = min(n - 1, round(rng.uniform(*fraction) * n))
    gone = set(rng.choice(np.arange(1, n), size=k, replace=False).tolist()) if k > 0 else set()
    return [f for i, f in enumerate(frames) if i not in gone]


def dropped(
    frames: Sequence[CaseFrame], rng: np.random.Generator, fraction: tuple[float, float] = (0.2, 0.3)
) -> list[CaseFrame]:
    """20–30 % of the frames removed at random (never the first); the others keep their true stamps."""
    return _drop(frames, rng, fraction)


def fixed_rate(
    frames: Sequence[CaseFrame],
    rng: np.random.Generator,
    fraction: tuple[float, float] = (0.2, 0.3),
    period_s: float | None = None,
) -> list[CaseFrame]:
    """The frames of :func:`dropped`, stamped ``period_s`` apart (default: the input's
    :func:`nominal_period`) from the first stamp on: the stamp gaps lie about the motion."""
    period = nominal_period(frames) if period_s is None else float(period_s)
    kept = _drop(frames, rng, fraction)
    t0 = kept[0].stamp
    return [
        dataclasses.replace(f, stamp=t0 + k * period, capture_time=f.true_time) for k, f in enumerate(kept)
    ]


def _victims(n: int, rng: np.random.Generator, fraction: float, start: int, pair: bool) -> list[int]:
    """Sorted indices ``>= start`` of about ``fraction · n`` frames (at least 2), one run of two
    consecutive ones among them when ``pair``."""
    pool = np.arange(start, n)
    if len(pool) < 2:
        return []
    count = min(len(pool), max(2, round(fraction * n)))
    chosen: set[int] = set()
    if pair and len(pool) >= 3:
        a = int(rng.integers(start, n - 1))
        chosen |= {a, a + 1}
    rest = [i for i in pool.tolist() if i not in chosen]
    extra = max(0, count - len(chosen))
    chosen |= set(rng.choice(rest, size=min(extra, len(rest)), replace=False).tolist())
    return sorted(chosen)


def black(
    frames: Sequence[CaseFrame], rng: np.random.Generator, fraction: float = 0.1, start: int = 3
) -> list[CaseFrame]:
    """About ``fraction`` of the frames from index ``start`` on (at least 2, one pair in a row)
    replaced by all-zero images of the camera's size; truth, stamp and odometry kept."""
    out = list(frames)
    for i in _victims(len(frames), rng, fraction, start, pair=True):
        f = frames[i]
        out[i] = dataclasses.replace(
            f, image=np.zeros((f.camera.height, f.camera.width), np.uint8), kind=BLACK
        )
    return out


def _png_bytes(image: object) -> bytes:
    """The frame as PNG (or its file's) bytes."""
    if isinstance(image, np.ndarray):
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise InputError("corrupt: cannot encode the frame as PNG")
        return buf.tobytes()
    if isinstance(image, (bytes, bytearray)):
        return bytes(image)
    return Path(image).read_bytes()  # type: ignore[arg-type]  # else a path (Path raises TypeError otherwise)


def corrupt(
    frames: Sequence[CaseFrame], rng: np.random.Generator, fraction: float = 0.1, start: int = 3
) -> list[CaseFrame]:
    """About ``fraction`` of the frames from index ``start`` on (at least 2) replaced, in turn, by
    zero-length bytes, 1 kB of random bytes and the frame's PNG cut in half; truth, stamp and
    odometry kept."""
    out = list(frames)
    for j, i in enumerate(_victims(len(frames), rng, fraction, start, pair=False)):
        f = frames[i]
        kind = j % 3
        if kind == 0:
            data = b""
        elif kind == 1:
            data = rng.bytes(1024)
        else:
            png = _png_bytes(f.image)
            data = png[: len(png) // 2]
        out[i] = dataclasses.replace(f, image=data, kind=CORRUPT)
    return out


def stop_and_go(
    frames: Sequence[CaseFrame],
    rng: np.random.Generator,
    stops: Sequence[float] = (1 / 3, 2 / 3),
    stop_frames: int = 10,
    period_s: float | None = None,
) -> list[CaseFrame]:
    """The robot stands still ``stop_frames`` frames after the frames at the fractions ``stops``
    of the stream: each stop repeats that frame (image, truth, odometry; kind :data:`STOPPED`)
    at ``period_s`` (default: :func:`nominal_period`) intervals, and every later stamp moves
    ``stop_frames · period_s`` later."""
    period = nominal_period(frames) if period_s is None else float(period_s)
    at = {min(len(frames) - 1, round(s * (len(frames) - 1))) for s in stops}
    out, shift = [], 0.0
    for i, f in enumerate(frames):
        out.append(dataclasses.replace(f, stamp=f.stamp + shift))
        if i in at:
            for k in range(1, stop_frames + 1):
                out.append(
                    dataclasses.replace(f, stamp=f.stamp + shift + k * period, kind=STOPPED, kidnapped=False)
                )
            shift += stop_frames * period
    return out


def _rechain(frames: Sequence[CaseFrame], order: Sequence[int], period: float) -> list[CaseFrame]:
    """``frames[order]`` restamped and with odometry re-chained: consecutive source frames keep
    their stamp gap and odometry increment; a jump (a kidnap) takes ``period`` and no odometry motion."""
    out: list[CaseFrame] = []
    for k, i in enumerate(order):
        f = frames[i]
        if k == 0:
            out.append(f)
            continue
        prev_i, prev = order[k - 1], out[-1]
        jump = i != prev_i + 1
        stamp = prev.stamp + (period if jump else frames[i].stamp - frames[prev_i].stamp)
        odometry, prev_source = f.odometry, frames[prev_i].odometry
        if prev.odometry is not None and f.odometry is not None and prev_source is not None:
            step = Pose.identity() if jump else f.odometry @ prev_source.inverse()
            odometry = step @ prev.odometry
        out.append(dataclasses.replace(f, stamp=stamp, odometry=odometry, kidnapped=jump))
    return out


def kidnap(frames: Sequence[CaseFrame], rng: np.random.Generator, at: float = 0.25) -> list[CaseFrame]:
    """After ``at`` of the stream, carried half of the rest ahead, then back (two kidnaps; module
    docstring); stamps go on, a kidnap taking one :func:`nominal_period`."""
    n = len(frames)
    if n < 4:
        raise InputError(f"kidnap: need at least 4 frames, got {n}")
    k = min(n - 2, max(1, round(at * n)))
    skip = (n - k) // 2  # as planarloc.synthetic.stream.stream_order(n, kidnap_at=k)
    order = [*range(k), *range(k + skip, n), *range(k, k + skip)]
    return _rechain(frames, order, nominal_period(frames))


def jitter(
    frames: Sequence[CaseFrame], rng: np.random.Generator, max_offset_s: float = 0.03
) -> list[CaseFrame]:
    """Each stamp moved by a uniform random offset in ``[-max_offset_s, max_offset_s]``; a stamp
    that would not come after the previous one is put 1 ms after it."""
    out: list[CaseFrame] = []
    for f in frames:
        stamp = f.stamp + float(rng.uniform(-max_offset_s, max_offset_s))
        if out and stamp <= out[-1].stamp:
            stamp = out[-1].stamp + 1e-3
        out.append(dataclasses.replace(f, stamp=stamp, capture_time=f.true_time))
    return out


# ---- registry -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class StreamCase:
    """A named stream perturbation.

    Attributes:
        name: the registry key.
        transform: ``(frames, rng) -> frames``.
        description: one line.
        kidnap: the stream has kidnaps (frames after one may be lost for a while by design).
    """

    name: str
    transform: Callable[[Sequence[CaseFrame], np.random.Generator], list[CaseFrame]]
    description: str
    kidnap: bool = False


CASES: dict[str, StreamCase] = {
    c.name: c
    for c in (
        StreamCase("default", default, "the stream as recorded"),
        StreamCase("dropped", dropped, "20-30 % of the frames removed, true stamps"),
        StreamCase("fixed-rate", fixed_rate, "20-30 % of the frames removed, stamps at the nominal rate"),
        StreamCase("black", black, "~10 % of the frames all-zero (truth kept)"),
        StreamCase("corrupt", corrupt, "~10 % of the frames empty, random or truncated bytes"),
        StreamCase("stop-and-go", stop_and_go, "two 10-frame stops: same image, truth and odometry"),
        StreamCase("kidnap", kidnap, "carried ahead after a quarter, later back (two kidnaps)", kidnap=True),
        StreamCase("jitter", jitter, "stamps off their true times by uniform +-30 ms"),
    )
}


def apply_case(name: str, frames: Sequence[CaseFrame], seed: int = 0) -> list[CaseFrame]:
    """The stream ``frames`` under case ``name`` with ``numpy.random.default_rng(seed)``.

    Raises:
        InputError: an unknown case (the message lists the known ones).
    """
    if name not in CASES:
        raise InputError(f"unknown stream case {name!r}; choose one of {', '.join(CASES)}")
    return CASES[name].transform(frames, np.random.default_rng(seed))
