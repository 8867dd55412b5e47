"""Stream cases: each named perturbation does what it says on a generated stream, is pure and
repeatable, and keeps truth and odometry where it promises to."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from planarloc.evaluation.sequence import ground_truth_jumps
from planarloc.evaluation.stream_cases import (
    BLACK,
    CASES,
    CORRUPT,
    FRAME,
    STOPPED,
    CaseFrame,
    apply_case,
    frames_from_stream,
    nominal_period,
)
from planarloc.features.images import decode_gray
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.map.posed_image import PosedImage
from planarloc.robust.pose_graph import so3_exp
from planarloc.synthetic.stream import make_stream, stream_order

CAM = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
N = 40
PERIOD = 0.1


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[CaseFrame]:
    """40 textured frames 0.3 m apart along a gentle curve, 10 Hz stamps, exact odometry."""
    folder = tmp_path_factory.mktemp("frames")
    rng = np.random.default_rng(7)
    images = []
    for k in range(N):
        path = folder / f"{k:03d}.png"
        cv2.imwrite(str(path), rng.integers(0, 256, (CAM.height, CAM.width), dtype=np.uint8))
        pose = Pose.from_center(so3_exp([[0, 0.02 * k, 0]])[0], [0.01 * k * k, 0, 0.3 * k])
        images.append(PosedImage(path.name, path, pose, CAM, k, timestamp=PERIOD * k))
    stream = make_stream(
        images, stream_order(N), np.random.default_rng(0), translation_std=0.0, rotation_std_deg=0.0
    )
    return frames_from_stream(stream)


def _same_source(a: CaseFrame, b: CaseFrame) -> bool:
    return a.name == b.name and pose_errors(a.truth, b.truth)[0] < 1e-12


def _motion(a: CaseFrame, b: CaseFrame) -> Pose:
    """``b``'s camera from ``a``'s, by the odometry."""
    return b.odometry @ a.odometry.inverse()


def _by_name(frames: list[CaseFrame]) -> dict[str, CaseFrame]:
    return {f.name: f for f in frames}


def test_frames_from_a_stream(frames: list[CaseFrame]) -> None:
    assert len(frames) == N and nominal_period(frames) == pytest.approx(PERIOD)
    f = frames[5]
    assert (
        isinstance(f.image, np.ndarray)
        and f.image.shape == (CAM.height, CAM.width)
        and f.image.dtype == np.uint8
    )
    assert f.kind == FRAME and not f.kidnapped and f.stamp == pytest.approx(0.5)
    # exact odometry: its increments are the true motions
    true = frames[6].truth @ frames[5].truth.inverse()
    assert pose_errors(_motion(frames[5], frames[6]), true)[0] < 1e-9


@pytest.mark.parametrize("name", list(CASES))
def test_every_case_is_pure_and_repeatable(frames: list[CaseFrame], name: str) -> None:
    before = [(f.name, f.stamp, f.kind, id(f.image)) for f in frames]
    a, b = apply_case(name, frames, seed=3), apply_case(name, frames, seed=3)
    assert [(f.name, f.stamp, f.kind) for f in a] == [(f.name, f.stamp, f.kind) for f in b]
    assert [(f.name, f.stamp, f.kind, id(f.image)) for f in frames] == before
    stamps = np.array([f.stamp for f in a])
    assert np.all(np.diff(stamps) > 0), "stamps must increase along every stream"
    original = _by_name(frames)
    for f in a:  # truth and camera always those of the source frame
        assert pose_errors(f.truth, original[f.name].truth)[0] < 1e-12 and f.camera == original[f.name].camera


def test_default_is_the_stream(frames: list[CaseFrame]) -> None:
    assert apply_case("default", frames) == frames


def test_dropped_removes_20_to_30_percent_and_keeps_true_stamps(frames: list[CaseFrame]) -> None:
    for seed in range(5):
        out = apply_case("dropped", frames, seed)
        assert 0.2 * N - 0.5 <= N - len(out) <= 0.3 * N + 0.5
        assert out[0] == frames[0]
        original = _by_name(frames)
        assert [f.name for f in out] == sorted(f.name for f in out)  # order kept
        assert all(f.stamp == original[f.name].stamp and f.odometry is original[f.name].odometry for f in out)
        assert max(np.diff([f.stamp for f in out])) > 1.5 * PERIOD  # the gaps show what is missing


def test_fixed_rate_stamps_are_even_while_the_truth_skips(frames: list[CaseFrame]) -> None:
    out = apply_case("fixed-rate", frames, seed=1)
    dropped = apply_case("dropped", frames, seed=1)
    assert [f.name for f in out] == [f.name for f in dropped]  # the same frames dropped
    assert np.allclose(np.diff([f.stamp for f in out]), PERIOD)  # evenly spaced stamps ...
    steps = [np.linalg.norm(b.truth.center - a.truth.center) for a, b in itertools.pairwise(out)]
    assert max(steps) > 1.9 * min(steps)  # ... over skipped motion
    assert out[0].stamp == frames[0].stamp
    # the capture times stay the true ones: a replay paced like the camera uses them
    assert [f.true_time for f in out] == [f.stamp for f in dropped]
    assert all(f.true_time == f.stamp for f in frames)


def test_black_frames_are_zero_images_with_their_truth(frames: list[CaseFrame]) -> None:
    out = apply_case("black", frames, seed=2)
    assert len(out) == N
    idx = [k for k, f in enumerate(out) if f.kind == BLACK]
    assert len(idx) >= 2 and min(idx) >= 3 and len(idx) <= 0.1 * N + 2
    assert any(b == a + 1 for a, b in itertools.pairwise(idx)), "one pair of black frames in a row"
    for k, (f, g) in enumerate(zip(out, frames)):
        assert f.stamp == g.stamp and f.odometry is g.odometry and _same_source(f, g)
        if k in idx:
            assert f.image.shape == (CAM.height, CAM.width) and not f.image.any()
        else:
            assert f.image is g.image and f.kind == FRAME


def test_corrupt_frames_are_bytes_no_decoder_takes(frames: list[CaseFrame]) -> None:
    out = apply_case("corrupt", frames, seed=4)
    bad = [f for f in out if f.kind == CORRUPT]
    assert len(bad) >= 3 and len(out) == N
    assert bad[0].image == b"" and len(bad[1].image) == 1024
    png = cv2.imencode(".png", _by_name(frames)[bad[2].name].image)[1].tobytes()
    assert bad[2].image == png[: len(png) // 2]
    for f in bad:
        assert isinstance(f.image, bytes)
        with pytest.raises(InputError):
            decode_gray(f.image)
    for f, g in zip(out, frames):
        assert f.stamp == g.stamp and f.odometry is g.odometry and _same_source(f, g)


def test_stop_and_go_repeats_a_frame_with_advancing_stamps(frames: list[CaseFrame]) -> None:
    out = apply_case("stop-and-go", frames)
    assert len(out) == N + 20
    stopped = [k for k, f in enumerate(out) if f.kind == STOPPED]
    assert len(stopped) == 20
    runs = [stopped[:10], stopped[10:]]
    for run in runs:
        assert run == list(range(run[0], run[0] + 10))  # one stop of 10 frames
        still = out[run[0] - 1]
        for k in run:
            f = out[k]
            assert f.name == still.name and f.image is still.image and f.odometry is still.odometry
            assert pose_errors(f.truth, still.truth)[0] == 0
        assert np.allclose(np.diff([out[k].stamp for k in [run[0] - 1, *run]]), PERIOD)
    # every later frame is stamped 1 s (2 s after the second stop) later than recorded
    original = _by_name(frames)
    last = out[-1]
    assert last.stamp == pytest.approx(original[last.name].stamp + 2.0)


def test_kidnap_jumps_twice_and_the_wheels_do_not_move(frames: list[CaseFrame]) -> None:
    out = apply_case("kidnap", frames)
    assert sorted(f.name for f in out) == sorted(f.name for f in frames)  # every frame once
    jumps = [k for k, f in enumerate(out) if f.kidnapped]
    assert len(jumps) == 2
    assert ground_truth_jumps([f.truth for f in out], min_jump_m=1.0) == [f.kidnapped for f in out]
    original = _by_name(frames)
    for k in range(1, len(out)):
        a, b = out[k - 1], out[k]
        gap = b.stamp - a.stamp
        if b.kidnapped:
            assert gap == pytest.approx(PERIOD)
            assert pose_errors(_motion(a, b), Pose.identity())[0] < 1e-9  # no odometry motion
        else:
            assert gap == pytest.approx(original[b.name].stamp - original[a.name].stamp)
            true = b.truth @ a.truth.inverse()
            assert pose_errors(_motion(a, b), true)[0] < 1e-9  # the true increment


def test_jitter_moves_stamps_by_at_most_30_ms(frames: list[CaseFrame]) -> None:
    out = apply_case("jitter", frames, seed=5)
    off = np.array([f.stamp - g.stamp for f, g in zip(out, frames)])
    assert np.all(np.abs(off) <= 0.03 + 1e-9) and np.std(off) > 0.005
    assert all(f.image is g.image and f.odometry is g.odometry for f, g in zip(out, frames))
    assert [f.true_time for f in out] == [g.stamp for g in frames]  # the truth kept apart


def test_unknown_case_and_degenerate_streams(frames: list[CaseFrame]) -> None:
    with pytest.raises(InputError, match="fixed-rate"):
        apply_case("nope", frames)
    with pytest.raises(InputError, match="at least 2"):
        nominal_period(frames[:1])
    with pytest.raises(InputError, match="at least 4"):
        apply_case("kidnap", frames[:3])
    assert apply_case("black", frames[:3]) == frames[:3]  # nothing after the start
