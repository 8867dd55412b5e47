"""Every TUM trajectory of a KITTI sequence with ``times.txt`` carries its times, not frame numbers
(#32): `evaluate --tum`, `evaluate --sequential --tum` (also when a kidnap re-times the stream),
`localize --tum` of image files, of the sequence folder and of a stream."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from _cli_runs import kitti_evaluate_argv, localize_argv, run
from kitti_layout import write_kitti_sequence

from planarloc.io.datasets import read_dataset

#: times.txt of the generated sequence: seconds that no frame number or 0.1 s clock could give
TIMES = [1317384506.40 + 0.1037 * k for k in range(12)]


@pytest.fixture(scope="module")
def kitti_seq(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny world's 12 map frames as a KITTI sequence (image_l/, poses.txt, calib.txt, times.txt)."""
    root = tmp_path_factory.mktemp("kitti_times") / "seq"
    frames = read_dataset(tiny_world / "map", "tum")
    assert len(frames) == len(TIMES) and frames[0].camera.model.value == "PINHOLE"
    write_kitti_sequence(frames, root, times=TIMES)
    return root


@pytest.fixture(scope="module")
def kitti_map(kitti_seq: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """`evaluate --tum` once (it builds the map of the even frames): (map, TUM folder)."""
    out = tmp_path_factory.mktemp("kitti_times_eval")
    assert run(kitti_evaluate_argv(kitti_seq, out / "map.db", "--tum", out / "tum")) == 0
    return out / "map.db", out / "tum"


def tum_times(path: Path) -> list[float]:
    return [float(line.split()[0]) for line in path.read_text().splitlines() if not line.startswith("#")]


def assert_times_of(stamps: list[float], frames: list[int], at_least: int) -> None:
    """``stamps`` are times.txt's times of some of ``frames``, in order, at least ``at_least``."""
    allowed = [TIMES[k] for k in frames]
    assert len(stamps) >= at_least and stamps == sorted(stamps)
    for t in stamps:
        assert min(abs(t - a) for a in allowed) < 1e-6, (t, allowed)


def test_evaluate_tum_first_column_is_times_txt(kitti_map: tuple[Path, Path]) -> None:
    _, tum = kitti_map
    est, gt = tum_times(tum / "estimate.txt"), tum_times(tum / "groundtruth.txt")
    assert est == gt
    assert_times_of(est, [1, 3, 5, 7, 9, 11], at_least=5)


@pytest.mark.parametrize(
    "extra, at_least", [([], 3), (["--kidnap-at", "2", "--simulate-odometry"], 2)], ids=["stream", "kidnap"]
)
def test_evaluate_sequential_tum_first_column_is_times_txt(
    kitti_seq: Path, kitti_map: tuple[Path, Path], tmp_path: Path, extra: list, at_least: int
) -> None:
    db, _ = kitti_map
    sequential = ("--sequential", "--fixes", "wait", *extra, "--tum", tmp_path / "tum")
    assert run(kitti_evaluate_argv(kitti_seq, db, *sequential)) == 0
    est, gt = tum_times(tmp_path / "tum" / "estimate.txt"), tum_times(tmp_path / "tum" / "groundtruth.txt")
    assert est == gt
    assert_times_of(est, [1, 3, 5, 7, 9, 11], at_least=at_least)


def test_localize_image_files_and_sequence_folder_carry_times_txt(
    kitti_seq: Path, kitti_map: tuple[Path, Path], tmp_path: Path
) -> None:
    db, _ = kitti_map
    files = [kitti_seq / "image_l" / f"{k:06d}.png" for k in (1, 4, 7)]
    tracks = ("--structure", "tracks", "--out", tmp_path / "p.txt")
    assert run(localize_argv(db, *files, *tracks, "--tum", tmp_path / "files.tum")) == 0
    assert_times_of(tum_times(tmp_path / "files.tum"), [1, 4, 7], at_least=3)
    # the whole sequence folder, named image_l/00000k.png
    tracks = ("--structure", "tracks", "--out", tmp_path / "q.txt")
    assert run(localize_argv(db, kitti_seq, *tracks, "--tum", tmp_path / "folder.tum")) == 0
    assert_times_of(tum_times(tmp_path / "folder.tum"), list(range(12)), at_least=10)


def test_localize_stream_carries_times_txt(
    kitti_seq: Path, kitti_map: tuple[Path, Path], tmp_path: Path
) -> None:
    db, _ = kitti_map
    stream = ("--sequence", kitti_seq / "image_l", "--fixes", "wait")
    assert run(localize_argv(db, *stream, "--out", tmp_path / "p.txt", "--tum", tmp_path / "stream.tum")) == 0
    assert_times_of(tum_times(tmp_path / "stream.tum"), list(range(12)), at_least=6)


def test_without_times_txt_the_frame_number_stays(
    kitti_seq: Path, kitti_map: tuple[Path, Path], tmp_path: Path
) -> None:
    """No times.txt: nothing is invented, the TUM time is the number in the file name (documented)."""
    db, _ = kitti_map
    copy = tmp_path / "seq"
    shutil.copytree(kitti_seq, copy)
    (copy / "times.txt").unlink()
    image = copy / "image_l" / "000003.png"
    assert run(localize_argv(db, image, "--out", tmp_path / "p.txt", "--tum", tmp_path / "t.tum")) == 0
    assert tum_times(tmp_path / "t.tum") == [3.0]
