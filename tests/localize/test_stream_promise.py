"""Every pose a stream gives keeps its promise — within ``3·position_std_m + 5 cm`` of the truth,
never beyond 1 m, whatever its status — on a rendered camera-rate stream under the cases a robot
meets: stamps at a nominal rate over lost frames, jittered stamps, blank frames, stop-and-go,
corrupt frames, and fixes that arrive late."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planarloc.features.images import read_gray
from planarloc.geometry.pose import pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.localize.sequence import SequenceConfig, SequenceLocalizer
from planarloc.map.builder import build_map
from planarloc.robust.options import RansacOptions
from planarloc.synthetic.stream import make_stream, stream_order
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk

#: fixes two frames late, every other frame: as a background worker delivers them, but repeatable
LATE_FIXES = {"fixes": "wait", "fix_every": 2, "fix_delay": 2}


@pytest.fixture(scope="module")
def camera_rate_world(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    """The office at 320x240: 16 map frames, 40 query frames ~0.35 m and ~9° apart, 10 Hz stamps."""
    root = generate(
        shrunk(get_preset("office"), scale=0.5, n_map=16, n_query=40),
        tmp_path_factory.mktemp("world") / "office",
        seed=0,
    )
    path = root.parent / "map.db"
    build_map(read_dataset(root / "map", "tum"), path)
    queries = read_dataset(root / "query", "tum")
    return path, make_stream(queries, stream_order(len(queries)), np.random.default_rng(0))


def _run(
    map_path: Path, frames: list, stamps: list[float], images: list | None = None, **config: object
) -> list:
    """(frame, estimate) of each frame streamed with ``stamps`` (and ``images`` instead of the frames')."""
    loc = Localizer(map_path, LocalizerConfig(ransac=RansacOptions(structure="tracks")))
    out = []
    with SequenceLocalizer(loc, SequenceConfig(**config)) as seq:
        for k, (f, stamp) in enumerate(zip(frames, stamps)):
            image = read_gray(f.image.path) if images is None or images[k] is None else images[k]
            out.append((f, seq.step(image, f.image.camera, stamp)))
    return out


def _check_promises(run: list, min_good: int) -> None:
    """Every pose given as usable keeps its promise; at least ``min_good`` are within 0.25 m / 10°."""
    good = 0
    for f, e in run:
        if not e.success:
            continue
        t, r = pose_errors(e.pose, f.image.cam_from_world)
        assert t < 1.0, (e.stamp, e.status, t)
        assert t <= 3 * e.position_std_m + 0.05, (e.stamp, e.status, t, e.position_std_m)
        good += t < 0.25 and r < 10
    assert good >= min_good, good


def test_stamps_at_a_nominal_rate_over_lost_frames(camera_rate_world: tuple) -> None:
    """Every third frame is lost but the stamps go on at 10 Hz: the stamp gaps lie about the
    motion by a factor of two; visual odometry's length is then doubted, not believed."""
    map_path, frames = camera_rate_world
    kept = [f for k, f in enumerate(frames) if k % 3 != 2]
    run = _run(map_path, kept, [0.1 * k for k in range(len(kept))], **LATE_FIXES)
    _check_promises(run, min_good=len(kept) // 3)


def test_jittered_stamps(camera_rate_world: tuple) -> None:
    map_path, frames = camera_rate_world
    rng = np.random.default_rng(1)
    stamps = [f.stamp + rng.uniform(-0.03, 0.03) for f in frames]
    run = _run(map_path, frames, stamps, **LATE_FIXES)
    _check_promises(run, min_good=len(frames) // 2)


def test_blank_frames_are_lost_with_a_reason_and_the_stream_goes_on(camera_rate_world: tuple) -> None:
    map_path, frames = camera_rate_world
    blank = {8, 9, 20}
    shape = read_gray(frames[0].image.path).shape
    images = [np.zeros(shape, np.uint8) if k in blank else None for k in range(len(frames))]
    run = _run(map_path, frames, [f.stamp for f in frames], images, **LATE_FIXES)
    for k, (_, e) in enumerate(run):
        if k in blank:
            assert e.status == "lost" and "blank frame" in e.message and not e.success
    _check_promises(run, min_good=len(frames) // 2)
    # the frames after a blank one are tracked across the gap and localized again
    assert any(e.status == "localized" for _, e in run[10:14])


def test_stop_and_go(camera_rate_world: tuple) -> None:
    """The robot stands still for a second twice: the same view, stamps going on."""
    map_path, frames = camera_rate_world
    stream = []
    for k, f in enumerate(frames[:24]):
        stream += [f] * (10 if k in (6, 15) else 1)
    run = _run(map_path, stream, [0.1 * k for k in range(len(stream))], **LATE_FIXES)
    _check_promises(run, min_good=len(stream) // 2)


def test_background_fixes_keep_the_promise(camera_rate_world: tuple) -> None:
    map_path, frames = camera_rate_world
    kept = [f for k, f in enumerate(frames) if k % 4 != 3]
    run = _run(map_path, kept, [0.1 * k for k in range(len(kept))])
    _check_promises(run, min_good=1)


def test_a_corrupt_frame_is_an_error_and_the_stream_goes_on(camera_rate_world: tuple, tmp_path: Path) -> None:
    map_path, frames = camera_rate_world
    loc = Localizer(map_path, LocalizerConfig(ransac=RansacOptions(structure="tracks")))
    truncated = Path(frames[3].image.path).read_bytes()[:200]
    with SequenceLocalizer(loc, SequenceConfig(fixes="wait")) as seq:
        first = [seq.step(read_gray(f.image.path), f.image.camera, f.stamp) for f in frames[:3]]
        for bad in (b"", truncated, b"\x89PNG garbage"):
            with pytest.raises(InputError):
                seq.step(bad, frames[3].image.camera, frames[3].stamp)
        after = [(f, seq.step(read_gray(f.image.path), f.image.camera, f.stamp)) for f in frames[3:8]]
    assert all(e.success for e in first)
    _check_promises(after, min_good=4)


@pytest.mark.parametrize("odometry", [False, True])
def test_a_kidnap_is_lost_not_a_wrong_pose(camera_rate_world: tuple, odometry: bool) -> None:
    """Carried to the other side of the loop and back (the wheels do not turn): the view breaks,
    the frames are lost until a fix of theirs settles it, no pose is given from the old place."""
    map_path, _ = camera_rate_world
    root = map_path.parent / "office"
    queries = read_dataset(root / "query", "tum")
    frames = make_stream(queries, stream_order(len(queries), kidnap_at=10), np.random.default_rng(0))
    loc = Localizer(map_path, LocalizerConfig(ransac=RansacOptions(structure="tracks")))
    run = []
    with SequenceLocalizer(loc, SequenceConfig(**LATE_FIXES)) as seq:
        for f in frames:
            odo = f.odometry if odometry else None
            run.append((f, seq.step(read_gray(f.image.path), f.image.camera, f.stamp, odo)))
    kidnaps = [k for k, (f, _) in enumerate(run) if f.kidnapped]
    assert len(kidnaps) == 2 and all(not run[k][1].success for k in kidnaps)
    # 40 % at least: the frames after each kidnap are lost until a fix settles them, and the office's
    # 9° turns between frames defeat visual odometry on some frames (stds above 0.3 m: lost)
    _check_promises(run, min_good=2 * len(frames) // 5)
